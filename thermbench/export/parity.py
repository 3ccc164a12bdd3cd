"""The parity check of an export: the C runtime against the Python model at every reading of the
held-out runs, per file variant, in double and in single precision (``-DTB_SINGLE``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from . import runtime
from .budget import SINGLE_FLAGS, TargetRefused
from .directory import replay_inputs
from .encoding import ExportError
from .samples import MAX_GAP_S
from .samples import process_samples, readings_queries


def python_predictions(model, ds, run: str, q: pd.DataFrame) -> np.ndarray:
    return model.predict_at(ds, run, q["t_s"].to_numpy(), q["axis_mm"].to_numpy())


def _float_hint(model) -> str:
    """Why single precision may not be enough for ``model``, and what to do instead."""
    from ..models.lssvm import PSOLSSVM

    lssvms = [model] if isinstance(model, PSOLSSVM) else [m for m in getattr(model, "models_", {}).values()
                                                           if isinstance(m, PSOLSSVM)]  # fmt: skip
    if lssvms:
        return (": an LSSVM's kernel weights are large and cancel, and float32 keeps 7 digits of each term; for a "
                "float target fit it on fewer samples (max_samples: fewer support vectors) or with a smaller penalty "
                "(gamma), or choose another family, or run the runtime in double (export.target=host)")  # fmt: skip
    return ": run this model on a double-precision build (export.target=host)"


def _sampling_failure(exc: Exception, ds, run: str, s: pd.DataFrame) -> Exception:
    """A replay the C runtime refused because the run's log is sampled too slowly for it (TB_E_SAMPLING:
    a gap over TB_MAX_GAP_S, the compensator's contract of a sample at least once a minute) as one line
    naming the run, its largest gap and what to do; any other failure as it is."""
    gaps = np.diff(s["t_s"].to_numpy(dtype=float))
    if "error -12" not in str(exc) or not gaps.size or float(gaps.max()) <= MAX_GAP_S:
        return exc
    name = getattr(ds, "path", None) or ds.metadata.machine.name
    return ExportError(f"{name}: run {run!r} is logged up to {gaps.max():g} s apart; the C runtime takes a sample at "
                       f"least every {MAX_GAP_S:g} s (the compensator samples its sensors that often), so it cannot "
                       "replay this log for the parity check: export with export.verify=false (no parity), or "
                       "verify on a dataset logged at least once a minute")  # fmt: skip


def _verify(tmp: Path, man: dict, models_py: dict, ds, runs: Sequence[str], tol_um: float, name: str,
            precision: str = "double") -> dict:  # fmt: skip
    """C runtime vs the Python model at every reading of ``runs`` (parity), per file variant, in
    double and in single precision (``-DTB_SINGLE``); the build of ``precision`` must be within ``tol_um``.
    And the single-precision build vs the double one at **every process sample** of every run (grid
    times of a bank's classifier, stream ends: where a time comparison that holds in double can fail
    in float; readings alone never fall on a grid time): within ``tol_um`` too when the target is float."""
    out: dict[str, Any] = {"runs": list(runs), "tolerance_um": tol_um, "precision": precision}
    exes = {"double": runtime.build("tb_replay"), "float": runtime.build("tb_replay", SINGLE_FLAGS)}
    for variant, model in models_py.items():
        file_variant = "model" if variant == "bank" else variant
        worst, n, err_c, err_py = {"double": 0.0, "float": 0.0}, 0, [], []
        every, n_samples, where = 0.0, 0, None  # float vs double at every process sample
        for run in runs:
            q = readings_queries(ds, run)
            py = python_predictions(model, ds, run, q)
            s = process_samples(ds, run)
            # one replay per precision answers the readings and every process sample: the two query
            # sets merged in time order (tb_replay takes nondecreasing times), answers split back
            qs = pd.DataFrame({"t_s": s["t_s"].to_numpy(dtype=float), "axis_mm": s["axis_mm"].to_numpy(dtype=float)})
            merged = pd.concat([q[["t_s", "axis_mm"]].astype(float), qs], ignore_index=True)
            order = np.argsort(merged["t_s"].to_numpy(), kind="stable")  # stable: each set keeps its own order
            is_reading = order < len(q)
            files, s, cols, bank = replay_inputs(tmp, ds, run, file_variant, man, s)
            text = runtime.stream_text(s, cols, merged.iloc[order])  # one input, both builds
            total = {}
            for prec, exe in exes.items():
                try:
                    total[prec] = runtime.replay_text(exe, files, text, bank=bank)["total_um"].to_numpy()
                except runtime.RuntimeFailed as exc:
                    raise _sampling_failure(exc, ds, run, s) from None
                at_readings = total[prec][is_reading]
                worst[prec] = max(worst[prec], float(np.max(np.abs(at_readings - py))))
                if prec == precision:
                    err_c.append(q["error_um"].to_numpy() - at_readings)
            n += len(q)
            err_py.append(q["error_um"].to_numpy() - py)
            d = np.abs(total["float"][~is_reading] - total["double"][~is_reading])
            if d.size and float(d.max()) > every:
                every, where = float(d.max()), (run, float(qs["t_s"].iloc[int(np.argmax(d))]))
            n_samples += len(qs)
        key = file_variant
        out[key] = {"max_abs_diff_um": worst["double"], "float_max_abs_diff_um": worst["float"], "n_readings": n,
                    "float_vs_double_every_sample_max_abs_um": every, "n_samples": n_samples,
                    "heldout_rmse_um_c": float(np.sqrt(np.mean(np.concatenate(err_c) ** 2))),
                    "heldout_rmse_um_python": float(np.sqrt(np.mean(np.concatenate(err_py) ** 2)))}  # fmt: skip
        if worst[precision] > tol_um:
            build, err = ("", ExportError) if precision == "double" else (" in single precision (-DTB_SINGLE)", TargetRefused)
            raise err(f"{name} ({variant}): the C runtime{build} differs from the Python model by {worst[precision]:.4g} um "
                      f"on held-out runs {list(runs)}, above parity_tol_um={tol_um}"
                      f"{_float_hint(model) if precision == 'float' else ''}")  # fmt: skip
        if precision == "float" and every > tol_um:
            raise TargetRefused(f"{name} ({variant}): the C runtime in single precision (-DTB_SINGLE) differs from the "
                                f"double build by {every:.4g} um at t = {where[1]:g} s of run {where[0]!r} (every process "
                                f"sample of {list(runs)} compared), above parity_tol_um={tol_um}{_float_hint(model)}")  # fmt: skip
    if "reduced" in out:
        out["reduced_cost_um"] = out["reduced"]["heldout_rmse_um_python"] - out["model"]["heldout_rmse_um_python"]
    return out
