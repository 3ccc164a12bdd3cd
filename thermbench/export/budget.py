"""The compensators an export is for (:data:`TARGETS`: the C runtime's precision there and the
budget beyond which an export is refused) and whether an export fits: its footprint against the
target's budget (:func:`footprint`), its files and state arenas in the target's build, and its
instructions per control cycle measured on the emulated Cortex-M4F."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from . import runtime
from .directory import replay_inputs
from .encoding import ExportError


class TargetRefused(ExportError):
    """The model does not meet its export target (:data:`TARGETS`): precision or budget."""


#: the compensators an export is for: the C runtime's precision there, and the budget it is refused
#: beyond (None: reported in the manifest's footprint only). cortex-m4f: seed 002's STM32F407
#: (Cortex-M4F, single-precision FPU, 1 MB flash, 128 KB main SRAM), thermbench.export.target
TARGETS = {
    "host": {"precision": "double", "budget": None},
    "cortex-m4f": {"precision": "float", "budget": {"ram_bytes": 16 * 1024, "file_bytes": 64 * 1024,
                                                     "cycle_insn": 100_000, "physics_update_insn": 50_000,
                                                     "prediction_insn": 200_000, "image_bytes": 64 * 1024}},
}


#: the C runtime in single precision (tb_runtime.h), as the Cortex-M4F target builds it
SINGLE_FLAGS = ("-DTB_SINGLE",)


#: seed 002's compensator, an STM32F407 (1 MB flash, 192 KB RAM, 168 MHz): the budget per model
BUDGET = {"file_bytes": 64 * 1024, "ram_bytes": 16 * 1024, "small_file_bytes": 1024}
SMALL_KINDS = ("MLR_CURVE", "MLR_SEED001", "CLASSIFIER")


def footprint(model_dir: Path, man: dict) -> dict:
    """File bytes and RAM (state arena + model handles) as the C runtime reports them, against
    :data:`BUDGET` (MLR files and the classifier <= 1 KB). Instruction counts: benchmarks/bench_export.py."""
    if man["kind"] == "bank":
        entries = [man["bank"]["classifier_file"], *man["bank"]["members"]]
        names = [man["bank"]["classifier"], *[m["file"] for m in man["bank"]["members"]]]
    else:
        entries = [man["files"]["model"]]
        names = [man["files"]["model"]["file"]]
    try:
        inf = runtime.info([Path(model_dir) / n for n in names])
    except runtime.RuntimeUnavailable as exc:  # export.verify=false works without gcc; RAM is then unknown
        return {"file_bytes": int(sum(e["bytes"] for e in entries)), "ram_bytes": None, "budget": BUDGET,
                "within_budget": None, "over_budget": [], "note": f"RAM not measured: {exc}"}  # fmt: skip
    ram = int(inf["state_bytes"].sum() + inf["model_bytes"].sum())
    over = [f"{n}: {e['bytes']} B file" for n, e in zip(names, entries)
            if e["bytes"] > (BUDGET["small_file_bytes"] if e["kind"] in SMALL_KINDS else BUDGET["file_bytes"])]  # fmt: skip
    if ram > BUDGET["ram_bytes"]:
        over.append(f"{ram} B RAM")
    return {"file_bytes": int(inf["file_bytes"].sum()), "ram_bytes": ram, "budget": BUDGET,
            "within_budget": not over, "over_budget": over}  # fmt: skip


def _check_target(model_dir: Path, man: dict, target: str, name: str) -> dict:
    """The export's files and state arenas in the target's build (the host's 64-bit pointers make
    the arenas a little larger than on a 32-bit target), refused beyond the target's budget."""
    budget = TARGETS[target]["budget"]
    files = ([man["bank"]["classifier"], *[m["file"] for m in man["bank"]["members"]]] if man["kind"] == "bank"
             else [f["file"] for f in man["files"].values()])  # fmt: skip
    inf = runtime.info([Path(model_dir) / f for f in files], SINGLE_FLAGS if TARGETS[target]["precision"] == "float" else ())
    arena = int(inf["state_bytes"].sum()) if man["kind"] == "bank" else int(inf["state_bytes"].max())
    over = [f"{f}: {b} B file" for f, b in zip(files, inf["file_bytes"]) if b > budget["file_bytes"]]
    if arena > budget["ram_bytes"]:
        why = (f"the bank's {len(files) - 1} members each keep their own state ({', '.join(map(str, inf['state_bytes'][1:]))} B)"
               if man["kind"] == "bank" else f"its state arena")  # fmt: skip
        over.append(f"{arena} B of state arena, above the target's {budget['ram_bytes']} B ({why})")
    if over:
        raise TargetRefused(f"{name}: does not fit the {target} target: {'; '.join(over)}. Export a smaller model "
                          f"(a global model instead of a bank, a shorter window_s for a GRU) or for export.target=host")  # fmt: skip
    return {"arena_bytes": arena, "file_bytes": [int(b) for b in inf["file_bytes"]], "budget": budget}


def _measure_on_target(model_dir: Path, man: dict, ds, runs: Sequence[str], name: str) -> dict:
    """Each file variant in single precision on the emulated Cortex-M4F (:mod:`.target`, QEMU) over
    **every** parity run, answering a query at every process sample: its worst instructions per
    control cycle and per prediction over all runs (with the run and the time of the worst cycle),
    the end-of-stream finish call on its own, arena, stack and the one-kind image's flash, refused
    beyond the budget (one physics update: ``physics_update_insn``); and its answers against the
    host's double build at every sample (``parity_vs_host_double_um``)."""
    from . import target as tgt

    budget = TARGETS["cortex-m4f"]["budget"]
    try:
        tgt.toolchain()
    except runtime.RuntimeUnavailable as exc:
        raise ExportError(f"{name}: export.target=cortex-m4f measures the model on the emulated M4: {exc}") from None
    out: dict[str, Any] = {"runs": list(runs), "queries": "every process sample"}
    over = []
    host = runtime.build("tb_replay")
    for variant in (["model"] if man["kind"] == "bank" else list(man["files"])):
        kind = man["kind"] if man["kind"] == "bank" else man["files"][variant]["kind"]
        m: dict[str, Any] = {"cycle_insn_max": 0, "prediction_insn_max": 0, "finish_insn_max": 0, "arena_bytes": 0,
                             "stack_bytes": 0, "parity_vs_host_double_um": 0.0, "n_samples": 0}  # fmt: skip
        for run in runs:
            files, samples, temps, bank = replay_inputs(model_dir, ds, run, variant, man)
            q = pd.DataFrame({"t_s": samples["t_s"].to_numpy(), "axis_mm": samples["axis_mm"].to_numpy()})
            got, rep = tgt.replay(files, samples, temps, q, precision="float", arena_bytes=budget["ram_bytes"])
            if rep["rc"] != 0:
                over.append(f"{variant}: the firmware stopped on run {run!r} ({rep['end']})")
                break
            ref = runtime.replay(files, samples, temps, q, bank=bank, exe=host)
            m["parity_vs_host_double_um"] = max(m["parity_vs_host_double_um"],
                                                float(np.max(np.abs(got["total_um"].to_numpy() - ref["total_um"].to_numpy()))))  # fmt: skip
            if rep.get("step_insn_max", 0) > m["cycle_insn_max"]:
                m["cycle_insn_max"], m["cycle_worst_run"] = rep["step_insn_max"], run
            for key, what in (("prediction_insn_max", "predict_insn_max"), ("finish_insn_max", "finish_insn_max"),
                              ("arena_bytes", "arena_bytes"), ("stack_bytes", "stack_bytes")):  # fmt: skip
                m[key] = max(m[key], int(rep.get(what, 0)))
            m["n_samples"] += len(samples)
        m["image_bytes"] = None if man["kind"] == "bank" else tgt.image(files[0], "float").flash_bytes
        out[variant] = m
        cyc = budget["physics_update_insn"] if kind == "PHYSICS" else budget["cycle_insn"]
        for what, v, lim in (("control cycle", m["cycle_insn_max"], cyc), ("prediction", m["prediction_insn_max"],
                             budget["prediction_insn"]), ("one-kind image", m["image_bytes"] or 0, budget["image_bytes"])):  # fmt: skip
            if v > lim:
                at = f" (worst on run {m['cycle_worst_run']!r})" if what == "control cycle" else ""
                over.append(f"{variant}: {what} {v} {'B' if what.endswith('image') else 'instructions'} > {lim}{at}")
    if over:
        hint = (" (a GRU's prediction runs window_s / step_s + 1 lags of 3 x hidden x (hidden + sensors) "
                "multiply-adds: fewer lags or hidden units)" if '"GRU"' in json.dumps([man.get("files"), man.get("bank")]) else "")  # fmt: skip
        raise TargetRefused(f"{name}: over the cortex-m4f budget, measured on the emulated M4 in float over every sample "
                            f"of {list(runs)}: {'; '.join(over)}{hint}")  # fmt: skip
    return out
