"""How many of LinuxCNC's sample programs ``thermbench precompensate`` compensates, with and
without flattening by LinuxCNC's interpreter (issue 23).

    .venv/bin/python benchmarks/precompensate_samples.py --model models/benchmark/seed000_x__physics__global.joblib \
        [--dataset seed000_x] [--programs /usr/share/linuxcnc/ncfiles] [--verify 3]

Every ``*.ngc`` of ``--programs`` (the ``ncfiles`` directory that Debian's linuxcnc-uspace
installs: 56 programs) goes through :func:`thermbench.precompensate.run_precompensate` twice:
``flatten=never`` (the line reader alone) and ``flatten=auto`` (LinuxCNC's ``rs274`` where the
reader cannot follow the program). Each outcome is one of: compensated (at least one X move
revised), no X move, or refused (the one-line reason, grouped). ``--verify N`` replays the first
N flattened, compensated programs in the simulator that made ``--dataset``.
"""

from __future__ import annotations

import argparse
import collections
import re
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from thermbench.errors import user_errors  # noqa: E402
from thermbench.precompensate import run_precompensate  # noqa: E402


def outcome(program: Path, model: Path, out: Path, dataset: str, flatten: str, verify: bool = False):
    try:
        res = run_precompensate(program, model, out, dataset=dataset, flatten=flatten, truth="auto" if verify else None)
    except user_errors() as exc:
        msg = str(exc)
        if re.search(r"finds no move|no G0/G1 move on axis|takes no time on axis", msg):
            return "no X move", msg, None
        return "refused", msg, None
    n = int(res.moves["compensate"].sum())
    return ("compensated" if n else "no X move"), f"{n} moves", res


def group(msg: str) -> str:
    for key, label in (("rs274 refused", "rs274 refused the program"), ("has no plain G-code", "canonical call not flattened"),
                       ("not plain G-code words", "parameters/expressions/O-codes"), ("G20", "inch"),
                       ("no motion mode", "axis word without G0/G1"), ("G2", "arcs"), ("G3", "arcs")):
        if key in msg:
            return label
    return msg.split(": ", 1)[-1][:70]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", required=True)
    ap.add_argument("--dataset", default="seed000_x")
    ap.add_argument("--programs", default="/usr/share/linuxcnc/ncfiles")
    ap.add_argument("--verify", type=int, default=0)
    a = ap.parse_args()
    programs = sorted(Path(a.programs).glob("*.ngc"))
    print(f"{len(programs)} programs in {a.programs}")
    with tempfile.TemporaryDirectory() as tmp:
        for flatten in ("never", "auto"):
            counts, reasons, verified = collections.Counter(), collections.Counter(), []
            for p in programs:
                out = Path(tmp) / f"{flatten}_{p.stem}.ngc"
                kind, msg, res = outcome(p, Path(a.model), out, a.dataset, flatten)
                counts[kind] += 1
                if kind == "refused":
                    reasons[group(msg)] += 1
                if flatten == "auto" and kind == "compensated" and res.settings.get("flattened") and len(verified) < a.verify:
                    _, _, vres = outcome(p, Path(a.model), Path(tmp) / f"v_{p.stem}.ngc", a.dataset, flatten, verify=True)
                    v = vres.verification
                    verified.append(f"    {p.name}: {v['moves']} move ends, max |error| {v['max_abs_before_um']:.2f} -> "
                                    f"{v['max_abs_after_um']:.2f} um, RMS {v['rms_before_um']:.2f} -> {v['rms_after_um']:.2f} um")
            print(f"flatten={flatten}: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
            for r, n in reasons.most_common():
                print(f"    refused, {r}: {n}")
            if verified:
                print("  --verify (the original motion replayed in the simulator):")
                print("\n".join(verified))
    return 0


if __name__ == "__main__":
    sys.exit(main())
