"""Revising a program: each G0/G1 target moved by the predicted error (:func:`precompensate`;
incremental blocks get the increment that puts the axis on the compensated point), the program's
text rewritten (:func:`program_text`), and the check in the simulator (:func:`verify_in_simulator`:
the original and the revised motion replayed on a :class:`~thermbench.sim.model.ScrewThermalModel`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..data.schema import Metadata
from ..models.base import ThermalErrorModel
from ..sim.model import Motion, ScrewThermalModel
from .program import PrecompError, Program, Unsupported, _flatten_reason, _read_program, parse_program
from .timing import _model_drive, _sample, _waypoints, plan_motion, predict_thermal_errors, resolve_metadata


# ------------------------------------------------------------------ rewrite ---
def _format(value: float, decimals: int) -> str:
    s = f"{value:.{decimals}f}"
    return s[1:] if s.startswith("-") and float(s) == 0 else s


def _rewrite(
    program: Program, new_target_mm: dict[int, float], min_decimals: int
) -> tuple[str, dict[int, tuple[float, float]]]:
    """The program text with the axis word of block i (index in ``program.blocks``)
    set so that its absolute end point is ``new_target_mm[i]`` (rounded); other text
    untouched. Returns the text and, per rewritten block, (written number, absolute end)."""
    edits, written = _edits(program, new_target_mm, min_decimals)
    return "".join(apply_edits(program.lines, edits)), written


def apply_edits(lines: list[str], edits: list[tuple[int, int, int, str]]) -> list[str]:
    """``lines`` with each edit ``(line index, start, end, text)`` put in place of that span; the
    edits of one line (several axes' words) are applied from the right, so their spans hold."""
    out = list(lines)
    for i, s0, s1, text in sorted(edits, key=lambda e: (e[0], e[1]), reverse=True):
        body = out[i].rstrip("\r\n")
        out[i] = body[:s0] + text + body[s1:] + out[i][len(body):]
    return out


def _edits(
    program: Program, new_target_mm: dict[int, float], min_decimals: int
) -> tuple[list[tuple[int, int, int, str]], dict[int, tuple[float, float]]]:
    """The edits of :func:`_rewrite` (``(line index, start, end, text)``) and what they write."""
    edits: list[tuple[int, int, int, str]] = []
    written: dict[int, tuple[float, float]] = {}
    pos = program.start_mm  # where the rewritten program has put the axis
    for i, b in enumerate(program.blocks):
        if b.span is None:
            continue  # a dwell
        if i not in new_target_mm:  # not compensated: its own word, as written
            value = b.target_mm - b.start_mm if b.incremental else b.target_mm
            pos = (pos if pos is not None else b.start_mm) + value if b.incremental else b.target_mm
            continue
        # in the program's own units: mm, or inches under G20 with one more decimal (1e-5 in = 0.25 um)
        u = b.mm_per_unit
        decimals = max(b.decimals, min_decimals + (1 if u != 1.0 else 0))
        if b.incremental:
            base = pos if pos is not None else b.start_mm
            value = round((new_target_mm[i] - base) / u, decimals)
            end = base + value * u
        else:
            value = round(new_target_mm[i] / u, decimals)
            end = value * u
        edits.append((b.line - 1, *b.span, _format(value, decimals)))
        written[i] = (value, end)
        pos = end
    return edits, written


@dataclass
class PrecompResult:
    """What :func:`precompensate` did.

    ``text``: the rewritten program; ``moves``: :func:`plan_motion`'s table plus
    ``predicted_error_um`` (at the move end, at the target), ``new_target_mm``
    (the absolute end point written, program coordinates) and ``written_value``
    (the number written: absolute, or the increment for G91), NaN for blocks not
    compensated; ``process``: the planned process log; ``unsupported``: lines
    passed through with what was not interpreted; ``notes``: warnings.
    """

    source: str
    text: str
    moves: pd.DataFrame
    process: pd.DataFrame
    unsupported: list[Unsupported]
    program: Program
    settings: dict
    model_name: str
    notes: list[str] = field(default_factory=list)
    verification: dict | None = None


def precompensate(
    program_text: str,
    model: ThermalErrorModel,
    dataset_metadata_source,
    axis: str = "X",
    rapid_mm_min: float = 10000.0,
    sample_s: float = 1.0,
    start_s: float = 0.0,
    start_mm: float | None = None,
    work_offset_mm: float = 0.0,
    ambient_C: float = 20.0,
    decimals: int = 4,
    source: str = "<program>",
) -> PrecompResult:
    """Revise the program so that each G0/G1 move lands where its target was meant
    to be once the thermal error is added (seed 003 §1: compensation by revising
    the NC program before machining, from the planned operation only).

    For every G0/G1 block with the axis word the model predicts the thermal error
    e (µm) at the move's end time at its axis position; the new absolute target is
    ``target - e / 1000`` written with ``max(decimals as written, decimals)``
    decimals (G91 blocks: the increment that ends there). ``model``: a fitted
    thermbench model reading only the motion (physics: ambient held at
    ``ambient_C``; ar_seed003 on feed); ``dataset_metadata_source``: the dataset
    it was trained on (:func:`resolve_metadata`). Other options: :func:`parse_program`
    and :func:`plan_motion`.
    """
    decimals = check_decimals(decimals)
    meta = resolve_metadata(dataset_metadata_source)
    _model_drive(model, meta)  # a model that cannot be driven fails before the program is read
    program = parse_program(program_text, axis, source, start_mm, work_offset_mm)
    moves, process = plan_motion(program, rapid_mm_min, sample_s, start_s, work_offset_mm)

    comp = moves["compensate"].to_numpy()
    e = predict_thermal_errors(
        model, meta, process, moves.loc[comp, "t_end_s"], moves.loc[comp, "axis_target_mm"], ambient_C,
        notes=f"planned motion of {source}",
    )  # fmt: skip
    idx = np.flatnonzero(comp)
    wanted = {int(i): float(moves["target_mm"].iloc[i] - ei / 1000.0) for i, ei in zip(idx, e)}
    text, written = _rewrite(program, wanted, decimals)

    moves = moves.copy()
    moves["predicted_error_um"] = np.nan
    moves.loc[comp, "predicted_error_um"] = e
    moves["new_target_mm"] = [written[i][1] if i in written else np.nan for i in range(len(moves))]
    moves["written_value"] = [written[i][0] if i in written else np.nan for i in range(len(moves))]

    notes = []
    fast = [b for b in program.blocks if b.feed_mm_min is not None and b.feed_mm_min > float(rapid_mm_min)]
    if fast:
        notes.append(f"{len(fast)} move(s) programmed faster than the rapid feed {float(rapid_mm_min):g} mm/min (F"
                     f"{max(b.feed_mm_min for b in fast):g} mm/min at line {fast[0].line} ...): timed at the rapid feed, "
                     "the machine's top speed (--rapid)")  # fmt: skip
    if axis.upper() != str(meta.machine.axis).upper():
        notes.append(
            f"the program's axis {axis.upper()} is compensated with a model of machine axis {meta.machine.axis}"
        )
    ends = [(r.condition.start_mm, r.condition.end_mm) for r in meta.runs.values()
            if r.condition is not None and r.condition.start_mm is not None and r.condition.end_mm is not None]
    lo = min((a for a, _ in ends), default=-np.inf)  # format 2 without strokes: no travel to compare with
    hi = max((b for _, b in ends), default=np.inf)
    tx = moves.loc[comp, "axis_target_mm"]
    if tx.min() < lo - 0.5 or tx.max() > hi + 0.5:
        notes.append(
            f"targets reach {tx.min():g}..{tx.max():g} mm (axis), beyond the travel of the training runs "
            f"({lo:g}..{hi:g} mm): the predictions there are extrapolations"
        )
    settings = {
        "axis": axis.upper(),
        "rapid_mm_min": float(rapid_mm_min),
        "sample_s": float(sample_s),
        "start_s": float(start_s),
        "start_mm": start_mm,
        "work_offset_mm": float(work_offset_mm),
        "ambient_C": float(ambient_C),
        "decimals": decimals,
    }
    name = type(model).__name__
    return PrecompResult(source, text, moves, process, program.unsupported, program, settings, name, notes)


# ------------------------------------------------------------- verification ---
def truth_from_metadata(metadata: Metadata) -> ScrewThermalModel:
    """The simulator model a simulated dataset was made with (its ``simulation``
    block: core, effects, numerics), for :func:`verify_in_simulator`."""
    from ..sim.registry import effects_from_config
    from ..sim.parts import CoreParams, Material, Numerics, Screw

    sim = (metadata.model_extra or {}).get("simulation")
    if not isinstance(sim, dict) or "core" not in sim:
        raise PrecompError(
            f"dataset of machine {metadata.machine.name!r} was not simulated (no 'simulation' block with the core "
            f"parameters in metadata.yaml): there is no simulator truth to verify against"
        )
    screw = metadata.screw.model_dump(exclude_none=True)
    screw.pop("fixed_end_axis_mm", None)
    screw = {k: screw[k] for k in ("length_m", "diameter_m", "nut_length_m", "fixed_bearing_length_m", "mounting")}
    m = metadata.material
    return ScrewThermalModel(
        Screw(**screw),
        Material(m.alpha_per_K, m.density_kg_m3, m.heat_capacity_J_kgK),
        CoreParams(**sim["core"]),
        effects_from_config(sim.get("effects") or {}),
        Numerics(**(sim.get("numerics") or {})),
    )


def simulate_true_errors(
    result: PrecompResult, truth: ScrewThermalModel, ambient_C: float | None = None
) -> pd.DataFrame:
    """Per compensated move: the truth's thermal error over the ORIGINAL program's
    motion (sampled at the truth's fine step) at the move end, before (axis at the
    commanded target x: ``error_before_um = e(t, x)``) and after (axis commanded to
    the rewritten target x', read back from the rewritten text: the axis sits at
    x' + e(t, x'), ``residual_um = (x' - x)·1000 + e(t, x')``)."""
    if not isinstance(truth, ScrewThermalModel):
        raise PrecompError(f"truth: expected a ScrewThermalModel (thermbench.sim), got {type(truth).__name__}")
    s = result.settings
    moves = result.moves
    start_s = s["start_s"]
    t_end = float(moves["t_end_s"].iloc[-1])
    t_w, x_w, f_seg = _waypoints(moves, start_s)
    t = np.arange(start_s, t_end, truth.numerics.dt_s)
    if t_end - t[-1] > 1e-9:
        t = np.append(t, t_end)  # the program end: the axis stops there
    x, f = _sample(t_w, x_w, f_seg, t)
    ambient = s["ambient_C"] if ambient_C is None else float(ambient_C)
    hist = truth.run(Motion(t, x, f), ambient_C=ambient, duration_s=t_end - start_s)

    rewritten = parse_program(result.text, s["axis"], result.source, s["start_mm"], s["work_offset_mm"])
    if len(rewritten.blocks) != len(result.program.blocks):
        raise PrecompError(f"{result.source}: the rewritten program has different blocks than the original")  # a bug
    comp = moves["compensate"].to_numpy()
    # a row per block (one axis planned alone), or a row per step of several axes' time line (its block column)
    blocks = moves.loc[comp, "block"].to_numpy(int) if "block" in moves else np.flatnonzero(comp)
    new_axis = np.array([b.target_mm for b in rewritten.blocks])[blocks] + s["work_offset_mm"]
    te = moves.loc[comp, "t_end_s"].to_numpy()
    xa = moves.loc[comp, "axis_target_mm"].to_numpy()
    before = hist.error_um(te, xa)
    after = (new_axis - xa) * 1000.0 + hist.error_um(te, new_axis)
    return pd.DataFrame(
        {
            "line": moves.loc[comp, "line"].to_numpy(),
            "t_end_s": te,
            "axis_target_mm": xa,
            "axis_new_target_mm": new_axis,
            "predicted_error_um": moves.loc[comp, "predicted_error_um"].to_numpy(),
            "error_before_um": before,
            "residual_um": after,
        }
    )


def verify_in_simulator(result: PrecompResult, truth_model: ScrewThermalModel, ambient_C: float | None = None) -> dict:
    """Replay in the simulator (:func:`simulate_true_errors`) and sum up over the
    compensated move ends: max |error| and RMS before and after, their reduction (%),
    and the model's prediction error against the truth (max |e_model - e_true|)."""
    tab = simulate_true_errors(result, truth_model, ambient_C)
    b, a = tab["error_before_um"].to_numpy(), tab["residual_um"].to_numpy()
    rms = lambda v: float(np.sqrt(np.mean(v**2)))  # noqa: E731
    out = {
        "moves": int(len(tab)),
        "max_abs_before_um": float(np.max(np.abs(b))),
        "rms_before_um": rms(b),
        "max_abs_after_um": float(np.max(np.abs(a))),
        "rms_after_um": rms(a),
        "max_abs_prediction_error_um": float(np.max(np.abs(tab["predicted_error_um"].to_numpy() - b))),
    }
    for key in ("max_abs", "rms"):
        before = out[f"{key}_before_um"]
        out[f"reduction_{key}_pct"] = 100.0 * (1.0 - out[f"{key}_after_um"] / before) if before > 0 else math.nan
    return out


def program_text(program_path: Path, axes: dict[str, tuple[float | None, float]], flatten: str, tool_table=None,
                 ini=None):  # fmt: skip
    """The program's text to compensate, and the flattening it went through (:func:`run_precompensate`'s
    ``flatten``): ``(text, the rs274 result or None, the note that says so or None)``. ``axes``: the
    axes the reader must follow, each with its start position (None: its first absolute target) and
    work offset (:func:`parse_program`)."""
    text = _read_program(program_path)
    if flatten not in ("auto", "always", "never"):
        raise PrecompError(f"--flatten: expected auto, always or never, got {flatten!r}")
    reason = None
    if flatten == "auto":
        reason = next((r for a, (s0, w) in axes.items() if (r := _flatten_reason(text, a, str(program_path), s0, w))), None)
    if flatten != "always" and reason is None:
        return text, None, None
    from ..linuxcnc.rs274 import flatten as rs274_flatten, rs274_path

    if rs274_path() is None:
        if flatten == "always":
            raise PrecompError(f"{program_path}: --flatten always needs LinuxCNC's rs274 (apt-get install "
                               "--no-install-recommends linuxcnc-uspace)")  # fmt: skip
        for a, (s0, w) in axes.items():
            parse_program(text, a, str(program_path), s0, w)  # the reader's own error, if any
        return text, None, None
    flat = rs274_flatten(program_path, tool_table=None if tool_table is None else Path(tool_table),
                         ini=None if ini is None else Path(ini))  # fmt: skip
    if flat.moves == 0:
        raise PrecompError(f"{program_path}: LinuxCNC's interpreter finds no move in it; nothing to compensate")
    note = (f"flattened with LinuxCNC's rs274 ({reason or '--flatten always'}): {flat.canonical_calls} "
            f"canonical calls -> {flat.moves} straight moves ({flat.arcs} arcs in chords), in {flat.units}; "
            "the output is the flattened program, compensated")  # fmt: skip
    return flat.text, flat, note


def check_decimals(decimals) -> int:
    """``decimals`` as an integer >= 1, or the one-line error."""
    try:
        value = int(decimals)
    except (TypeError, ValueError):
        raise PrecompError(f"decimals: expected an integer >= 1, got {decimals!r}") from None
    if value < 1:
        raise PrecompError(f"decimals: expected an integer >= 1, got {decimals!r}")
    return value