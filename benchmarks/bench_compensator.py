"""The compensator's control loop under load: cycles at a 10 ms period against ``thermbench
sim-cnc`` running in its own process on 127.0.0.1, at 100x real time so that every cycle
sees a new process sample and steps the model in the C runtime (the worst case).

Prints, per block of 1000 cycles after a warm-up block and as the median over the blocks:
the cycle time (read + model + write) p50/p90/p99/max, the start lateness against the
absolute deadlines, the mean period and the lateness trend over the block (drift); and the
process's resident memory sampled every 0.5 s with its trend per 1000 cycles (growth).

    python benchmarks/bench_compensator.py [MODEL_DIR] [--blocks 3] [--period 0.01]

MODEL_DIR defaults to exports/benchmark/seed001_vmc_x__mlr_seed002__global (``make demo`` or
``thermbench export`` writes it).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

DEFAULT_MODEL = Path("exports/benchmark/seed001_vmc_x__mlr_seed002__global")


def rss_kb() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def run(model_dir: Path, endpoint: str, nodes: Path, log: Path, cycles: int, period_s: float):
    from thermbench.compensator.client import Compensator

    comp = Compensator(model_dir, endpoint, nodes, {"period_s": period_s, "max_cycles": cycles, "log": str(log)})
    mem: list[tuple[float, int]] = []

    async def sample():
        while True:
            mem.append((time.time(), rss_kb()))
            await asyncio.sleep(0.5)

    sampler = asyncio.ensure_future(sample())
    summary = await comp.run()
    sampler.cancel()
    return summary, mem


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("model_dir", nargs="?", default=str(DEFAULT_MODEL))
    ap.add_argument("--blocks", type=int, default=3, help="measured blocks of 1000 cycles (after one warm-up block)")
    ap.add_argument("--period", type=float, default=0.01, help="cycle period, s")
    ap.add_argument("--speed", type=float, default=100.0, help="sim-cnc speed (100: a new 1 s sample every 10 ms)")
    args = ap.parse_args()
    model_dir = Path(args.model_dir)
    if not (model_dir / "manifest.json").exists():
        print(f"{model_dir}: no exported model; run `make demo` or `thermbench export` first", file=sys.stderr)
        return 2
    import logging

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    n_blocks = args.blocks + 1
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        port = free_port()
        endpoint = f"opc.tcp://127.0.0.1:{port}/bench"
        nodes = tmp / "nodes.yaml"
        server = subprocess.Popen([sys.executable, "-m", "thermbench", "sim-cnc", "--endpoint", endpoint, "run=valid1",
                                   f"speed={args.speed:g}", "start=immediate", f"write_nodes={nodes}", f"out_dir={tmp / 'sim'}"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)  # fmt: skip
        try:
            deadline = time.monotonic() + 120
            while True:  # the nodes file is written just before the server listens
                if server.poll() is not None:
                    print(f"sim-cnc stopped: {server.stderr.read()}", file=sys.stderr)
                    return 1
                if nodes.exists():
                    try:
                        socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                        break
                    except OSError:
                        pass
                if time.monotonic() > deadline:
                    print("sim-cnc did not come up within 120 s", file=sys.stderr)
                    return 1
                time.sleep(0.1)
            summary, mem = asyncio.run(run(model_dir, endpoint, nodes, tmp / "cycles.csv", 1000 * n_blocks, args.period))
            log = pd.read_csv(tmp / "cycles.csv")
        finally:
            server.terminate()
            server.wait(timeout=30)
    print(f"compensator {summary['model']}: {summary['cycles']} cycles at {1e3 * args.period:.0f} ms against sim-cnc "
          f"({args.speed:g}x real time); flags {summary['flags']}")  # fmt: skip
    t = np.array([m[0] for m in mem])
    kb = np.array([m[1] for m in mem], dtype=float)
    rows = []
    log["block"] = np.arange(len(log)) // 1000
    for b, g in log.groupby("block"):
        if b == 0 or len(g) < 1000:
            continue  # warm-up
        d, late, k = g["cycle_ms"].to_numpy(), g["late_ms"].to_numpy(), g["cycle"].to_numpy()
        wall = g["wall_s"].to_numpy()
        rows.append({"block": b, "p50_ms": np.percentile(d, 50), "p90_ms": np.percentile(d, 90),
                     "p99_ms": np.percentile(d, 99), "max_ms": d.max(), "late_p99_ms": np.percentile(late, 99),
                     "mean_period_ms": 1e3 * np.polyfit(k, wall, 1)[0],
                     "drift_ms": np.polyfit(k, late, 1)[0] * (k[-1] - k[0]), "over_period": int((d > 1e3 * args.period).sum()),
                     "model_steps": int(g["t_s"].diff().fillna(0).gt(0).sum()),
                     "rss_end_MiB": kb[np.searchsorted(t, wall[-1], side="right") - 1] / 1024})  # fmt: skip
    table = pd.DataFrame(rows)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    med = table.median(numeric_only=True)
    print(f"median over {len(table)} blocks: cycle p50 {med['p50_ms']:.3f} ms, p90 {med['p90_ms']:.3f} ms, p99 {med['p99_ms']:.3f} ms, "
          f"max {med['max_ms']:.3f} ms; mean period {med['mean_period_ms']:.4f} ms; drift {med['drift_ms']:+.3f} ms per block")  # fmt: skip
    after = t >= log["wall_s"].iloc[min(999, len(log) - 1)]  # after the warm-up block
    if after.sum() > 3:
        slope = np.polyfit(t[after], kb[after], 1)[0] * 1000 * args.period
        print(f"resident memory: {kb[after][0] / 1024:.1f} MiB after warm-up, {kb[-1] / 1024:.1f} MiB at the end; "
              f"trend {slope:+.1f} KiB per 1000 cycles ({after.sum()} samples)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
