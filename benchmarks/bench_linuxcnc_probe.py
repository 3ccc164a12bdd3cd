"""The LinuxCNC closed loop with a probe: the tool's thermal error after compensation,
with one probe per simulated hour and without, on a duty cycle the model was not trained on.

The model: seed 002's MLR (mlr_seed002) fitted on one loading state of seed001_vmc_x (``--state``,
default state4: strokes over 0-210 mm at 8000 mm/min). The program: a reciprocating X stroke over
``--stroke`` (default 240-450 mm, valid3's travel) at ``--feed`` (10000 mm/min), none of which the
model saw, then a stop while the screw cools. The same LinuxCNC run (thermbench linuxcnc sim, 120x
thermal clock) twice: open loop, and with the plant's simulated touch probe every ``--every`` machine
seconds netted to the component's probe-um / probe-valid pins (the bias + gain filter of
docs/intervals.md, conf/linuxcnc_component.yaml's probe noise). Printed: the thermal error at the tool
before compensation and after it (RMS and max over every process sample, the plant's simulator), and
the ratio with / without probes (target: <= 0.5).

Needs LinuxCNC (linuxcnc-uspace); as root, ``--user`` names the unprivileged user it runs as.

    python benchmarks/bench_linuxcnc_probe.py --user thermbench-lcnc [--every 3600] [--repeats 45]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import stat
import sys
import sysconfig
import tempfile
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--user", default=None)
    ap.add_argument("--state", default="state4")
    ap.add_argument("--stroke", default="240,450")
    ap.add_argument("--feed", type=float, default=10000.0)
    ap.add_argument("--repeats", type=int, default=45)
    ap.add_argument("--dwell", type=float, default=20.0, help="wall seconds of the stop at the end")
    ap.add_argument("--every", type=float, default=3600.0, help="machine seconds between probes")
    ap.add_argument("--keep", action="store_true", help="keep the runs' directories (printed)")
    ap.add_argument("--noise", choices=["default", "estimated"], default="default",
                    help="the filter's noise: conf/linuxcnc_component.yaml's (measured on fl_thermal), or estimated "
                         "(thermbench.bench.adapt.estimate_noise) from the model's residuals on the dataset's other runs")
    ap.add_argument("--gain0", type=float, default=0.1, help="with --noise estimated: the gain's std before the first probe")
    a = ap.parse_args()

    from thermbench.bench import datasets
    from thermbench.export import ExportOptions, export_model
    from thermbench.linuxcnc.sim import blocking_dirs, run_sim
    from thermbench.models.mlr import MLRSeed002

    ds = datasets.load_benchmark("seed001_vmc_x")
    work = Path(tempfile.mkdtemp(prefix="thermbench-lcnc-probe-"))
    work.chmod(0o755)
    repo = Path(__file__).resolve().parents[1]
    blocked = blocking_dirs([Path(sys.executable).resolve(), Path(sysconfig.get_paths()["purelib"]), repo]) if os.geteuid() == 0 else []
    modes = {d: stat.S_IMODE(d.stat().st_mode) for d in blocked}
    try:
        for d, m in modes.items():
            d.chmod(m | 0o001)
        export_model(MLRSeed002().fit(ds, [a.state]), work / "model", f"mlr-{a.state}", ds, [],
                     options=ExportOptions(onnx=False, verify=False))  # fmt: skip
        comp = {}
        if a.noise == "estimated":  # the model's residuals on runs it was not fitted on (none is the program run here)
            from thermbench.bench.adapt import estimate_noise

            m = MLRSeed002().fit(ds, [a.state])
            runs = []
            for r in [r for r in ds.run_ids if r != a.state]:
                e = ds.errors_run(r)
                runs.append((e["t_s"].to_numpy(float), e["error_um"].to_numpy(float) - m.predict(ds, r)))
            params = estimate_noise(runs, a.every, gain0=a.gain0)
            comp = {"probe": params.as_dict()}
            print(f"probe noise estimated on {len(runs)} runs: {params.as_dict()}")
        start, end = (float(v) for v in a.stroke.split(","))
        program = {"start_mm": start, "end_mm": end, "feed_mm_min": a.feed, "repeats": a.repeats, "dwell_s": a.dwell}
        out = {}
        for name, every in (("no probes", None), (f"probe every {a.every:g} s", a.every)):
            cfg = {"out_dir": str(work / name.replace(" ", "_")), "user": a.user, "program": program, "probe_every_s": every,
                   "component": comp}
            f = run_sim(work / "model", cfg, say=lambda line: None)
            out[name] = f
            t = f["tool"]
            print(f"{name:>22}: machine {t['machine_s'] / 3600:.2f} h, probes {t.get('probes', 0)}, tool error before "
                  f"compensation RMS {t['before_rms_um']:.2f} max {t['before_max_abs_um']:.2f} um, after RMS "
                  f"{t['after_rms_um']:.2f} max {t['after_max_abs_um']:.2f} um (run ok: {f['ok']})", flush=True)  # fmt: skip
        (no, yes) = (out[k]["tool"] for k in out)
        print(f"with / without probes: RMS {yes['after_rms_um'] / no['after_rms_um']:.2f}, "
              f"max {yes['after_max_abs_um'] / no['after_max_abs_um']:.2f} (target <= 0.5)")
        print(json.dumps({k: v["tool"] for k, v in out.items()}, default=float))
    finally:
        for d, m in modes.items():
            d.chmod(m)
        if a.keep:
            print(f"runs kept in {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
