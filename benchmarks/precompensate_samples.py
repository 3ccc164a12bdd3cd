"""How many of LinuxCNC's sample programs ``thermbench precompensate`` compensates, with and
without flattening by LinuxCNC's interpreter.

    # one axis, one model
    .venv/bin/python benchmarks/precompensate_samples.py --model models/benchmark/seed000_x__physics__global.joblib \
        [--dataset seed000_x] [--programs /usr/share/linuxcnc/ncfiles] [--verify 3]
    # every axis its own model: make demo's three physics models as X, Y and Z
    .venv/bin/python benchmarks/precompensate_samples.py --models-dir models/benchmark [--verify 3]
    .venv/bin/python benchmarks/precompensate_samples.py --models axes.yaml [--verify 3]

Every ``*.ngc`` of ``--programs`` (the ``ncfiles`` directory that Debian's linuxcnc-uspace
installs: 56 programs) goes through :func:`thermbench.precompensate.run_precompensate` (one axis)
or :func:`thermbench.precompensate.axes.run_precompensate_axes` (``--models``, ``--models-dir``)
twice: ``flatten=never`` (the line reader alone) and ``flatten=auto`` (LinuxCNC's ``rs274`` where
the reader cannot follow the program). Each outcome is one of: compensated (at least one move
revised), no move (on the axis / on any axis with a model), or refused (the one-line reason,
grouped, and with ``--list`` per program). A traceback is a bug and stops the script.
``--verify N`` replays the first N flattened, compensated programs in the simulator that made each
model's dataset (with ``--models``: the first N that revise more than one axis, every axis);
``--verify-programs a.ngc,b.ngc`` those instead.

``--models-dir DIR`` writes an axes file mapping X, Y and Z to DIR's physics models of seed000_x,
seed001_vmc_x and seed002_vmc655h_x (the three simulated axes ``make demo`` fits; their machines'
axes are all X: each model stands for one axis of a three-axis machine).
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
from thermbench.precompensate.axes import run_precompensate_axes  # noqa: E402

DEMO_AXES = {"X": "seed000_x", "Y": "seed001_vmc_x", "Z": "seed002_vmc655h_x"}


def outcome(program: Path, model: Path, out: Path, dataset: str, flatten: str, verify: bool, axes: bool):
    try:
        if axes:
            res = run_precompensate_axes(program, model, out, verify=verify, flatten=flatten)
        else:
            res = run_precompensate(program, model, out, dataset=dataset, flatten=flatten, truth="auto" if verify else None)
    except user_errors() as exc:
        msg = str(exc)
        if re.search(r"finds no move|no G0/G1 move on|takes no time", msg):
            return "no move", msg, None
        return "refused", msg, None
    if axes:
        return "compensated", ", ".join(f"{a} {int(r.moves['compensate'].sum())}" for a, r in res.axes.items()), res
    n = int(res.moves["compensate"].sum())
    return ("compensated" if n else "no move"), f"{n} moves", res


def group(msg: str) -> str:
    for key, label in (("rs274 refused", "rs274 refused the program"), ("has no plain G-code", "canonical call not flattened"),
                       ("not plain G-code words", "parameters/expressions/O-codes"), ("G20", "inch"),
                       ("G7 (lathe diameter mode)", "lathe diameter mode G7"),
                       ("no motion mode", "axis word without G0/G1"), ("G2", "arcs"), ("G3", "arcs")):
        if key in msg:
            return label
    return msg.split(": ", 1)[-1][:70]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", help="one model for X (a .joblib file)")
    src.add_argument("--models", help="an axes file (thermbench precompensate --models)")
    src.add_argument("--models-dir", help="make demo's models directory: X, Y, Z from its three simulated axes")
    ap.add_argument("--dataset", default="seed000_x")
    ap.add_argument("--programs", default="/usr/share/linuxcnc/ncfiles")
    ap.add_argument("--verify", type=int, default=0)
    ap.add_argument("--verify-programs", default=None, help="verify these compensated programs (comma-separated "
                    "file names) instead of the first --verify")  # fmt: skip
    ap.add_argument("--list", action="store_true", help="print every program's outcome")
    a = ap.parse_args()
    programs = sorted(Path(a.programs).glob("*.ngc"))
    print(f"{len(programs)} programs in {a.programs}")
    with tempfile.TemporaryDirectory() as tmp:
        model, axes = Path(a.model or a.models or ""), a.model is None
        if a.models_dir:
            d = Path(a.models_dir).resolve()
            missing = [str(d / f"{ds}__physics__global.joblib") for ds in DEMO_AXES.values()
                       if not (d / f"{ds}__physics__global.joblib").is_file()]  # fmt: skip
            if missing:
                ap.exit(2, f"precompensate_samples.py: error: {missing[0]}: no such model; run make demo first\n")
            model = Path(tmp) / "axes.yaml"
            model.write_text("".join(f"{ax}: {d / f'{ds}__physics__global.joblib'}\n" for ax, ds in DEMO_AXES.items()))
            print(f"axes: {model.read_text().strip()}".replace("\n", "; "))
        for flatten in ("never", "auto"):
            counts, reasons, verified, listing, n_verified = collections.Counter(), collections.Counter(), [], [], 0
            for p in programs:
                out = Path(tmp) / f"{flatten}_{p.stem}.ngc"
                kind, msg, res = outcome(p, model, out, a.dataset, flatten, False, axes)
                counts[kind] += 1
                listing.append(f"    {p.name}: {kind}: {msg}")
                if kind == "refused":
                    reasons[group(msg)] += 1
                many = axes and res is not None and len(res.axes) > 1
                if a.verify_programs:
                    chosen = p.name in a.verify_programs.split(",")
                else:
                    chosen = res is not None and res.settings.get("flattened") and (many or not axes) and n_verified < a.verify
                if flatten == "auto" and kind == "compensated" and chosen:
                    n_verified += 1
                    _, _, vres = outcome(p, model, Path(tmp) / f"v_{p.stem}.ngc", a.dataset, flatten, True, axes)
                    vs = vres.verification if axes else {vres.settings["axis"]: vres.verification}
                    for ax, v in vs.items():
                        verified.append(f"    {p.name} axis {ax}: {v['moves']} move ends, max |error| "
                                        f"{v['max_abs_before_um']:.2f} -> {v['max_abs_after_um']:.2f} um, RMS "
                                        f"{v['rms_before_um']:.2f} -> {v['rms_after_um']:.2f} um")  # fmt: skip
            print(f"flatten={flatten}: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
            for r, n in reasons.most_common():
                print(f"    refused, {r}: {n}")
            if a.list:
                print("\n".join(listing))
            if verified:
                print("  --verify (the original motion replayed in the simulator):")
                print("\n".join(verified))
    return 0


if __name__ == "__main__":
    sys.exit(main())
