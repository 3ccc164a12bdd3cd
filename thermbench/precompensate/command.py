"""``thermbench precompensate`` from files (:func:`run_precompensate`: the program, the model, the
revised program written beside the user's files without overwriting them) and its summary
(:func:`format_summary`).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ..outputs import check_output_file, write_text
from ..sim.model import ScrewThermalModel
from .program import PrecompError, Unsupported
from .revision import PrecompResult, precompensate, program_text, truth_from_metadata, verify_in_simulator
from .timing import resolve_metadata


def _load_model(path: Path):
    import joblib

    if path.is_dir():
        raise PrecompError(f"{path}: a directory; expected a fitted model file saved with joblib "
                           "(models/benchmark/<dataset>__<family>__<approach>.joblib)")  # fmt: skip
    if not path.is_file():
        raise PrecompError(
            f"{path}: no such model file; expected a fitted model saved with joblib "
            "(models/benchmark/<dataset>__<family>__<approach>.joblib)"
        )
    try:
        return joblib.load(path)
    except Exception as exc:  # any unpickling failure is the user's file
        raise PrecompError(f"{path}: not a joblib model file ({type(exc).__name__}: {exc})") from None


def run_precompensate(
    program_path,
    model_path,
    out_path,
    dataset=None,
    truth=None,
    axis: str = "X",
    rapid_mm_min: float = 10000.0,
    sample_s: float = 1.0,
    start_s: float = 0.0,
    start_mm: float | None = None,
    work_offset_mm: float = 0.0,
    ambient_C: float = 20.0,
    decimals: int = 4,
    flatten: str = "auto",
    tool_table=None,
    ini=None,
) -> PrecompResult:
    """``thermbench precompensate``: read the program and the joblib model, write the
    rewritten program to ``out_path`` (atomically; never over a file thermbench did not
    write: :func:`thermbench.outputs.output_file`), optionally verify.

    ``dataset``: what the model was trained on (:func:`resolve_metadata`); None
    infers it from a benchmark model file name ``<dataset>__<family>__<approach>``.
    ``truth``: None (no verification), ``"auto"`` (the simulator that made
    ``dataset``: :func:`truth_from_metadata`), a dataset name/directory, or a
    :class:`ScrewThermalModel`. The verification figures are in ``result.verification``.
    ``flatten``: ``"auto"`` runs LinuxCNC's interpreter (``rs274``, :mod:`thermbench.linuxcnc.rs274`)
    over a program the reader cannot follow (parameters, expressions, loops, subroutines) and
    compensates the flattened program; ``"always"`` also flattens a program it can follow (its arcs
    become compensated chords); ``"never"``.
    ``tool_table``: LinuxCNC's tool table for rs274 (None: tools 1..99 without offsets); ``ini``: the
    machine's LinuxCNC INI for rs274 (subroutine paths; its parameter file's work offsets). The
    lines a flattened program passes through name the line of the original they come from.
    """
    program_path, model_path, out_path = Path(program_path), Path(model_path), Path(out_path)
    text, flat, flat_note = program_text(program_path, {axis: (start_mm, work_offset_mm)}, flatten, tool_table, ini)
    if out_path.resolve() == program_path.resolve():
        raise PrecompError(f"{out_path}: the output would overwrite the input program; expected another file name")
    check_output_file(out_path, "part-program")  # an existing file thermbench did not write is refused now
    model = _load_model(model_path)
    if dataset is None:
        from ..bench import datasets

        dataset = datasets.of_key(model_path.stem)
        if dataset is None:
            raise PrecompError(
                f"{model_path}: cannot tell which dataset the model was trained on; expected --dataset NAME_OR_DIR"
            )
    meta = resolve_metadata(dataset)
    truth_model = None  # resolved first: a wrong --verify fails before anything is written
    if truth is not None:
        if isinstance(truth, ScrewThermalModel):
            truth_model = truth
        elif isinstance(truth, str) and truth == "auto":
            truth_model = truth_from_metadata(meta)
        else:
            truth_model = truth_from_metadata(resolve_metadata(truth))
    try:
        result = precompensate(
            text, model, meta, axis=axis, rapid_mm_min=rapid_mm_min, sample_s=sample_s, start_s=start_s,
            start_mm=start_mm, work_offset_mm=work_offset_mm, ambient_C=ambient_C, decimals=decimals,
            source=str(program_path),
        )  # fmt: skip
    except PrecompError as exc:  # a line of the flattened program: named by the user's line
        raise type(exc)(at_origin(str(exc), str(program_path), flat)) from None
    if flat is not None:
        result.notes.insert(0, flat_note)
        result.settings["flattened"] = True
        for u in result.unsupported:
            u.origin = flat.origin(u.line)
    write_text(out_path, result.text, "part-program")
    result.settings["out_path"] = str(out_path)
    if truth_model is not None:
        result.verification = verify_in_simulator(result, truth_model)
    return result


def at_origin(message: str, source: str, flat) -> str:
    """``message`` with each ``source:N`` (a line of the flattened program ``flat``) naming the line of
    the user's file it comes from: ``part.ngc:850 (line 997 of the flattened program)``."""
    if flat is None:
        return message
    folder = Path(source).parent

    def sub(m):
        origin = flat.origin(int(m.group(1)))
        where = f"{folder / origin}" if origin else source
        return f"{where} (line {m.group(1)} of the program as flattened by rs274)"

    return re.sub(rf"{re.escape(source)}:(\d+)", sub, message)


def _duration(seconds: float) -> str:
    m = int(round(seconds / 60.0))
    return f"{m // 60} h {m % 60:02d} min" if m >= 60 else f"{seconds / 60.0:.1f} min"


def notes_and_passed_through(notes: list[str], unsupported: list[Unsupported], max_lines: int) -> list[str]:
    """The summary's lines for the notes and the lines passed through (the first ``max_lines``)."""
    lines = [f"  note: {n}" for n in notes]
    if unsupported:
        lines.append(f"  passed through, not (fully) interpreted: {len(unsupported)} line(s)")
        for u in unsupported[:max_lines]:
            at = f"line {u.line}" + (f" (from {u.origin})" if u.origin else "")
            lines.append(f"    {at}: {u.text.strip()}  -- {u.reason}")
        if len(unsupported) > max_lines:
            lines.append(f"    ... and {len(unsupported) - max_lines} more")
    return lines


def format_summary(result: PrecompResult, verification: dict | None = None, max_lines: int = 20) -> str:
    """A few lines for the terminal: what was compensated, what passed through, and
    the verification figures (``verification`` or ``result.verification``)."""
    ver = verification if verification is not None else result.verification
    mv = result.moves
    comp = mv[mv["compensate"]]
    e = comp["predicted_error_um"].to_numpy()
    span = float(mv["t_end_s"].iloc[-1] - mv["t_start_s"].iloc[0])
    out = result.settings.get("out_path")
    head = f"precompensate {result.source}" + (f" -> {out}" if out else "")
    lines = [
        head,
        f"  axis {result.settings['axis']}, model {result.model_name}: {len(comp)} G0/G1 moves compensated over a "
        f"planned {_duration(span)} (rapid {result.settings['rapid_mm_min']:g} mm/min)",
        f"  predicted thermal error at the move ends: {e.min():+.2f} .. {e.max():+.2f} µm "
        f"(mean |e| {np.mean(np.abs(e)):.2f} µm); targets moved by -e/1000 mm",
    ]
    lines += notes_and_passed_through(result.notes, result.unsupported, max_lines)
    if ver:
        pct = lambda v: "n/a" if v is None or not math.isfinite(v) else f"{v:.0f} %"  # noqa: E731
        lines += [
            f"  verification in the simulator over {ver['moves']} move ends (original motion replayed):",
            f"    max |error| {ver['max_abs_before_um']:.2f} -> {ver['max_abs_after_um']:.2f} µm "
            f"(reduction {pct(ver['reduction_max_abs_pct'])})",
            f"    RMS         {ver['rms_before_um']:.2f} -> {ver['rms_after_um']:.2f} µm "
            f"(reduction {pct(ver['reduction_rms_pct'])})",
            f"    model vs truth at the move ends: max |difference| {ver['max_abs_prediction_error_um']:.2f} µm",
        ]
    return "\n".join(lines)