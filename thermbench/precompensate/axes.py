"""Pre-compensation of a whole part program: every feed axis with its own model (seed 003 §1).

:mod:`thermbench.precompensate` revises one axis with one model. A machine has a thermal model
per axis, and a program moves several at once, so here:

1. the program is read once per linear axis it names (X, Y, Z: :func:`~thermbench.precompensate.parse_program`,
   the same reader and the same refusals);
2. :func:`plan_axes` times it on **one time line**: a G0/G1 block takes its path length over all
   the axes it moves (``√(Δx² + Δy² + Δz²)``) at its feed (G0 and any faster feed at the rapid),
   a G4 its dwell; each axis's planned process log then has its own position and its own speed
   (``|Δaxis| / duration``), standing still while the others move;
3. each axis that has a model gets its G0/G1 targets revised by that model's predicted thermal
   error at the move's end (``target - e / 1000``), exactly as for one axis; an axis without a model
   is left as written, number for number;
4. a header comment at the top of the output lists which model revised which axis.

``thermbench precompensate PROGRAM --models axes.yaml --out OUT``; the file maps each axis to a
model (:func:`read_axes_file`). The flattening through LinuxCNC's ``rs274`` is the one-axis path's
(:func:`~thermbench.precompensate.program_text`), for every axis. Lathe programs: a radius program
(G8, the default) in the XZ plane (G18) is read as any other; in diameter mode (G7) the X words
are diameters, so the reader refuses it in one line and ``--flatten auto`` has LinuxCNC's ``rs274``
turn it into radii (the flattened program says G8). Full description:
docs/precompensate.md.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..data.schema import Metadata
from ..outputs import check_output_file, write_text
from .command import _load_model, notes_and_passed_through
from .program import PrecompError, Program, ProgramError, Unsupported, parse_program
from .revision import (
    PrecompResult, _edits, apply_edits, check_decimals, program_text, truth_from_metadata, verify_in_simulator,
)
from .timing import _check_positive, _model_drive, _sample, _waypoints, predict_thermal_errors, resolve_metadata

__all__ = ["AxisModel", "AxesResult", "format_axes_summary", "plan_axes", "precompensate_axes", "read_axes_file",
           "run_precompensate_axes"]  # fmt: skip

LINEAR_AXES = "XYZ"
_ENTRY_KEYS = {"model", "dataset", "start_mm", "work_offset_mm"}


@dataclass
class AxisModel:
    """One axis's model: ``model`` a fitted thermbench model reading only the motion, ``metadata`` the
    dataset it was trained on, ``label`` what the output's header calls it (its file)."""

    model: Any
    metadata: Metadata
    label: str
    start_mm: float | None = None  # the axis position before the first block (None: its first absolute target)
    work_offset_mm: float = 0.0  # axis position = program coordinate + this


def _unique_key_loader():
    import yaml

    class Loader(yaml.SafeLoader):
        """A SafeLoader that refuses a key given twice (YAML keeps the last one silently)."""

    def mapping(loader, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = loader.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"key {key!r} given twice", key_node.start_mark)
            seen.add(key)
        return yaml.SafeLoader.construct_mapping(loader, node, deep)

    Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    return Loader


_UniqueKeyLoader = _unique_key_loader()


def read_axes_file(path) -> dict[str, AxisModel]:
    """The axes file of ``--models``: a YAML mapping of axis letters to models,

    .. code-block:: yaml

        X: models/benchmark/seed000_x__physics__global.joblib
        Y: {model: models/benchmark/seed001_vmc_x__physics__global.joblib, work_offset_mm: 0}
        Z: {model: z.joblib, dataset: data/my_z_axis, start_mm: 50}

    A value is a model file (what ``--model`` takes) or a mapping with ``model`` and optionally
    ``dataset`` (what it was trained on; default: from a benchmark model file's name, as ``--model``),
    ``start_mm`` and ``work_offset_mm`` (``--start-mm`` and ``--work-offset`` for that axis). Relative
    paths are relative to the axes file's directory; the axis letters may be lower case. Every mistake
    names the file and the key (a YAML syntax error, the line)."""
    import yaml

    path = Path(path)
    try:
        raw = yaml.load(path.read_text(encoding="utf-8"), Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader)
    except OSError as exc:
        raise PrecompError(f"{path}: cannot read the axes file ({exc.strerror or exc}); expected a YAML file "
                           "mapping axes to models (X: model.joblib)") from None  # fmt: skip
    except UnicodeDecodeError:
        raise PrecompError(f"{path}: not UTF-8 text; expected a YAML file mapping axes to models (X: model.joblib)") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        what = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise PrecompError(f"{at}: not YAML ({what}); expected a mapping of axes to models (X: model.joblib)") from None
    if not isinstance(raw, dict) or not raw:
        raise PrecompError(f"{path}: expected a mapping of axes to models (X: model.joblib), got {type(raw).__name__}")
    out: dict[str, AxisModel] = {}
    for key, value in raw.items():
        axis = str(key).upper()
        where = f"{path}: key {key!r}"
        if axis not in LINEAR_AXES:
            raise PrecompError(f"{where}: expected a linear axis, one of {list(LINEAR_AXES)}")
        if axis in out:
            raise PrecompError(f"{where}: axis {axis} given twice")
        entry = {"model": value} if isinstance(value, str) else value
        if not isinstance(entry, dict) or "model" not in entry:
            raise PrecompError(f"{where}: expected a model file or a mapping with 'model', got {value!r}")
        unknown = sorted(set(entry) - _ENTRY_KEYS)
        if unknown:
            raise PrecompError(f"{where}: unknown key(s) {unknown}; expected {sorted(_ENTRY_KEYS)}")
        numbers = {}
        for k in ("start_mm", "work_offset_mm"):
            v = entry.get(k)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)):
                raise PrecompError(f"{where}: {k}: expected a number in mm, got {v!r}")
            numbers[k] = None if v is None else float(v)
        model_path = path.parent / str(entry["model"])
        try:
            model = _load_model(model_path)
        except PrecompError as exc:
            raise PrecompError(f"{where}: {exc}") from None
        dataset = entry.get("dataset")
        if dataset is None:
            from ..bench import datasets

            dataset = datasets.of_key(model_path.stem)
            if dataset is None:
                raise PrecompError(f"{where}: cannot tell which dataset {model_path} was trained on; expected "
                                   f"{{model: ..., dataset: NAME_OR_DIR}}")  # fmt: skip
        elif Path(str(dataset)).parts and (path.parent / str(dataset)).is_dir():
            dataset = path.parent / str(dataset)
        try:
            meta = resolve_metadata(dataset)
            _model_drive(model, meta)
        except PrecompError as exc:
            raise PrecompError(f"{where}: {exc}") from None
        out[axis] = AxisModel(model, meta, str(model_path), numbers["start_mm"], numbers["work_offset_mm"] or 0.0)
    return out


def plan_axes(
    programs: dict[str, Program],
    rapid_mm_min: float = 10000.0,
    sample_s: float = 1.0,
    start_s: float = 0.0,
    work_offset_mm: dict[str, float] | None = None,
) -> dict[str, tuple[pd.DataFrame, pd.DataFrame]]:
    """Time a program read once per axis (``programs``: axis -> :func:`parse_program` of the same
    text) on one time line, as the module docstring says; no acceleration, tool changes or spindle.

    Returns per axis ``(moves, process)`` in :func:`~thermbench.precompensate.plan_motion`'s columns,
    ``moves`` with a row per step of the time line (the axis's own block there, or ``hold`` while the
    others move; ``block`` the index in its :attr:`Program.blocks`, -1 for a hold), ``feed_mm_min`` the
    axis's own speed (0 at a dwell or a hold), and ``process`` its planned log every ``sample_s``.
    An axis the program never puts anywhere (only dwells) is left out.
    """
    rapid = _check_positive("rapid_mm_min", rapid_mm_min)
    sample = _check_positive("sample_s", sample_s, upper=1.0)
    offsets = {a: float((work_offset_mm or {}).get(a, 0.0)) for a in programs}
    at = {a: {b.line: (i, b) for i, b in enumerate(p.blocks)} for a, p in programs.items()}
    # the position before an axis's first block: its first known one (it is standing there)
    pos = {a: next((b.start_mm for b in p.blocks if not math.isnan(b.start_mm)), math.nan) for a, p in programs.items()}
    axes = [a for a in programs if not math.isnan(pos[a])]
    rows: dict[str, list[dict]] = {a: [] for a in axes}
    t = float(start_s)
    for line in sorted({n for a in axes for n in at[a]}):
        here = {a: at[a][line] for a in axes if line in at[a]}
        blocks = [b for _, b in here.values()]
        if blocks[0].kind == "G4":
            duration, feed = blocks[0].dwell_s, 0.0
        else:
            length = math.sqrt(sum((b.target_mm - b.start_mm) ** 2 for b in blocks))
            feed = rapid if blocks[0].feed_mm_min is None else min(blocks[0].feed_mm_min, rapid)
            duration = length / feed * 60.0
        for a in axes:
            i, b = here.get(a, (-1, None))
            start = pos[a] if b is None or math.isnan(b.start_mm) else b.start_mm
            target = start if b is None or b.kind == "G4" else b.target_mm
            rows[a].append({
                "line": line, "kind": "hold" if b is None else b.kind, "compensate": b is not None and b.compensate,
                "start_mm": start, "target_mm": target, "axis_start_mm": start + offsets[a],
                "axis_target_mm": target + offsets[a],
                "feed_mm_min": abs(target - start) / duration * 60.0 if duration > 0 else 0.0,
                "dwell_s": b.dwell_s if b is not None else 0.0, "t_start_s": t, "t_end_s": t + duration,
                "duration_s": duration, "block": i,
            })  # fmt: skip
            pos[a] = target
        t += duration
    if t - float(start_s) <= 0:
        raise PrecompError(f"{next(iter(programs.values())).source}: the program takes no time (all moves are zero-length)")
    grid = np.arange(float(start_s), t, sample)
    if t - grid[-1] > 1e-6:
        grid = np.append(grid, t)
    out = {}
    for a in axes:
        moves = pd.DataFrame(rows[a])
        t_w, x_w, f_seg = _waypoints(moves, float(start_s))
        axis_mm, feed_mm_min = _sample(t_w, x_w, f_seg, grid)
        out[a] = moves, pd.DataFrame({"t_s": grid, "axis_mm": axis_mm, "feed_mm_min": feed_mm_min})
    return out


@dataclass
class AxesResult:
    """What :func:`precompensate_axes` did: ``text`` the revised program (with its header), ``axes``
    per revised axis a :class:`~thermbench.precompensate.PrecompResult` (its moves on the common
    time line, its settings; each one's ``text`` is the whole revised program), ``as_written`` per axis
    left as written the reason, ``unsupported`` the lines passed through (every axis's reasons)."""

    source: str
    text: str
    axes: dict[str, PrecompResult]
    as_written: dict[str, str]
    unsupported: list[Unsupported]
    settings: dict
    notes: list[str] = field(default_factory=list)
    verification: dict[str, dict] = field(default_factory=dict)


def _header(models: dict[str, AxisModel], revised: dict[str, PrecompResult], as_written: dict[str, str]) -> list[str]:
    clean = lambda s: str(s).replace("(", "[").replace(")", "]")  # noqa: E731  (a comment cannot hold parentheses)
    lines = ["(thermbench precompensate: each axis's G0/G1 targets moved by -e/1000 mm, e its own model's "
             "predicted thermal error at the move's end)"]  # fmt: skip
    for a in LINEAR_AXES:
        if a in revised:
            m = models[a]
            n = int(revised[a].moves["compensate"].sum())
            lines.append(f"(axis {a}: {clean(m.label)}, {type(m.model).__name__} of machine "
                         f"{clean(m.metadata.machine.name)}, {n} moves revised)")  # fmt: skip
        elif a in as_written:
            lines.append(f"(axis {a}: as written, {clean(as_written[a])})")
    return lines


def precompensate_axes(
    program_text_: str,
    models: dict[str, AxisModel],
    rapid_mm_min: float = 10000.0,
    sample_s: float = 1.0,
    start_s: float = 0.0,
    ambient_C: float = 20.0,
    decimals: int = 4,
    source: str = "<program>",
) -> AxesResult:
    """Revise every axis of ``models`` by its own model on the program's one time line (module
    docstring); the options are :func:`~thermbench.precompensate.precompensate`'s."""
    decimals = check_decimals(decimals)
    if not models:
        raise PrecompError("models: expected at least one axis with a model")
    revised_before = re.search(r"^\s*\(thermbench precompensate:", program_text_, re.M)
    if revised_before:
        n = program_text_.count("\n", 0, revised_before.start()) + 1
        raise PrecompError(f"{source}:{n}: already revised by thermbench precompensate (its header); expected the "
                           "program as written (revising it again would subtract the errors twice)")  # fmt: skip
    programs, as_written, notes = {}, {}, []
    for a in LINEAR_AXES:
        try:
            m = models.get(a)
            programs[a] = parse_program(program_text_, a, source, m and m.start_mm, m.work_offset_mm if m else 0.0)
        except ProgramError as exc:
            if a in models:
                raise
            # an axis without a model that the reader cannot follow: left as written, its motion not timed
            as_written[a] = f"no model; its motion is not timed: {exc}"
    if not any(b.compensate for a in models for b in programs[a].blocks):
        raise PrecompError(f"{source}: no G0/G1 move on any axis with a model ({', '.join(sorted(models))}); "
                           "nothing to compensate")  # fmt: skip
    offsets = {a: models[a].work_offset_mm for a in models}
    plans = plan_axes(programs, rapid_mm_min, sample_s, start_s, offsets)
    edits, revised = [], {}
    named = list(programs)
    for a in LINEAR_AXES:
        if a not in models:
            if a in plans and any(b.compensate for b in programs[a].blocks):
                as_written[a] = "no model"
            continue
        if a not in plans or not any(b.compensate for b in programs[a].blocks):
            as_written[a] = "no G0/G1 move"
            continue
        m, (moves, process) = models[a], plans[a]
        comp = moves["compensate"].to_numpy()
        e = predict_thermal_errors(m.model, m.metadata, process, moves.loc[comp, "t_end_s"],
                                   moves.loc[comp, "axis_target_mm"], ambient_C,
                                   notes=f"planned motion of {source}, axis {a}")  # fmt: skip
        blocks = moves.loc[comp, "block"].to_numpy(int)
        wanted = {int(i): float(programs[a].blocks[i].target_mm - ei / 1000.0) for i, ei in zip(blocks, e)}
        ed, written = _edits(programs[a], wanted, decimals)
        edits += ed
        moves = moves.copy()
        moves["predicted_error_um"] = np.nan
        moves.loc[comp, "predicted_error_um"] = e
        moves["new_target_mm"] = [written[i][1] if i in written else np.nan for i in moves["block"]]
        moves["written_value"] = [written[i][0] if i in written else np.nan for i in moves["block"]]
        if a != str(m.metadata.machine.axis).upper():
            notes.append(f"axis {a} is compensated with a model of machine {m.metadata.machine.name}'s axis "
                         f"{m.metadata.machine.axis}")  # fmt: skip
        settings = {"axis": a, "rapid_mm_min": float(rapid_mm_min), "sample_s": float(sample_s),
                    "start_s": float(start_s), "start_mm": m.start_mm, "work_offset_mm": m.work_offset_mm,
                    "ambient_C": float(ambient_C), "decimals": decimals}  # fmt: skip
        revised[a] = PrecompResult(source, "", moves, process, programs[a].unsupported, programs[a], settings,
                                   type(m.model).__name__)  # fmt: skip
    if not revised:
        raise PrecompError(f"{source}: no G0/G1 move on any axis with a model ({', '.join(sorted(models))}); "
                           "nothing to compensate")  # fmt: skip
    lines = apply_edits(next(iter(programs.values())).lines, edits)
    eol = "\r\n" if lines and lines[0].endswith("\r\n") else "\n"
    at = 1 if lines and lines[0].strip() == "%" else 0  # a program between % lines: the header inside them
    if lines and not lines[-1].endswith("\n") and at >= len(lines):
        lines[-1] += eol
    header = _header(models, revised, as_written)
    lines[at:at] = [h + eol for h in header]
    text = "".join(lines)
    for r in revised.values():
        r.text = text
    merged: dict[int, Unsupported] = {}
    for a in named:
        for u in programs[a].unsupported:
            if u.line not in merged:
                merged[u.line] = Unsupported(u.line, u.text, u.reason)
            else:
                merged[u.line].reason += "; " + u.reason
    for u in merged.values():
        u.reason = _one_time_line(u.reason)
    settings = {"rapid_mm_min": float(rapid_mm_min), "sample_s": float(sample_s), "start_s": float(start_s),
                "ambient_C": float(ambient_C), "decimals": decimals, "header_lines": len(header),
                "header_at": at}  # fmt: skip
    return AxesResult(source, text, revised, as_written, [merged[k] for k in sorted(merged)], settings, notes)


def _one_time_line(reason: str) -> str:
    """One line's reasons from every axis's reading, said once for the one time line: an arc or cycle
    is followed on each axis and timed on its chord; ``G28 not interpreted (X not involved)`` per
    axis becomes one."""
    parts = list(dict.fromkeys(p.strip() for p in reason.split(";") if p.strip()))
    out, followed, uninvolved = [], {}, {}
    for p in parts:
        if m := re.fullmatch(r"(G[\d.]+) with ([XYZ]): end point followed, timed on the [XYZ] distance, not compensated", p):
            followed.setdefault(m.group(1), []).append(m.group(2))
        elif m := re.fullmatch(r"(G[\d.]+) not interpreted \(([XYZ]) not involved\)", p):
            uninvolved.setdefault(m.group(1), []).append(m.group(2))
        else:
            out.append(p)
    out = [p for p in out if not (m := re.fullmatch(r"(G[\d.]+) motion: not timed, not compensated", p)) or m.group(1)
           not in followed]  # fmt: skip
    out += [f"{g} with {', '.join(ax)}: end point followed, timed on its chord over the axes, not compensated"
            for g, ax in followed.items()]  # fmt: skip
    out += [f"{g} not interpreted ({', '.join(ax)} not involved)" for g, ax in uninvolved.items()]
    return "; ".join(out)


def run_precompensate_axes(
    program_path,
    axes_path,
    out_path,
    verify: bool = False,
    rapid_mm_min: float = 10000.0,
    sample_s: float = 1.0,
    start_s: float = 0.0,
    ambient_C: float = 20.0,
    decimals: int = 4,
    flatten: str = "auto",
    tool_table=None,
    ini=None,
) -> AxesResult:
    """``thermbench precompensate PROGRAM --models axes.yaml --out OUT``: read the axes file
    (:func:`read_axes_file`), flatten the program where the reader cannot follow it on some axis
    (:func:`~thermbench.precompensate.program_text`), revise it, write ``out_path`` atomically (never
    over a file thermbench did not write); ``verify``: replay each revised axis's original motion in
    the simulator that made its model's dataset (``result.verification[axis]``)."""
    program_path, out_path = Path(program_path), Path(out_path)
    if out_path.resolve() == program_path.resolve():
        raise PrecompError(f"{out_path}: the output would overwrite the input program; expected another file name")
    check_output_file(out_path, "part-program")
    models = read_axes_file(axes_path)
    truths = {a: truth_from_metadata(m.metadata) for a, m in models.items()} if verify else {}
    # flattened where the reader cannot follow an axis with a model (one without is left out of the time line)
    text, flat, note = program_text(program_path, {a: (m.start_mm, m.work_offset_mm) for a, m in models.items()}, flatten,
                                    tool_table, ini)  # fmt: skip
    from .command import at_origin

    try:
        result = precompensate_axes(text, models, rapid_mm_min, sample_s, start_s, ambient_C, decimals, str(program_path))
    except PrecompError as exc:  # a line of the flattened program: named by the user's line
        raise type(exc)(at_origin(str(exc), str(program_path), flat)) from None
    if flat is not None:
        result.as_written = {a: at_origin(r, str(program_path), flat) for a, r in result.as_written.items()}
        lines = result.text.splitlines(keepends=True)
        at, n = result.settings["header_at"], result.settings["header_lines"]
        for i in range(at, at + n):  # the header's "as written" reasons too; a comment holds no parentheses
            body = lines[i].rstrip("\r\n")
            inner = at_origin(body[1:-1], str(program_path), flat).replace("(", "[").replace(")", "]")
            lines[i] = f"({inner})" + lines[i][len(body):]
        result.text = "".join(lines)
        for r in result.axes.values():
            r.text = result.text
        result.notes.insert(0, note)
        result.settings["flattened"] = True
        for u in result.unsupported:
            u.origin = flat.origin(u.line)
    write_text(out_path, result.text, "part-program")
    result.settings["out_path"] = str(out_path)
    result.settings["models"] = {a: m.label for a, m in models.items()}
    for a, r in result.axes.items():
        if a in truths:
            result.verification[a] = verify_in_simulator(r, truths[a])
    return result


def format_axes_summary(result: AxesResult, max_lines: int = 20) -> str:
    """A few lines for the terminal: per axis what revised it and the verification figures."""
    out = result.settings.get("out_path")
    lines = [f"precompensate {result.source}" + (f" -> {out}" if out else "")]
    span = max(float(r.moves["t_end_s"].iloc[-1] - r.moves["t_start_s"].iloc[0]) for r in result.axes.values())
    lines.append(f"  one time line over every axis: a planned {span / 60.0:.1f} min (rapid {result.settings['rapid_mm_min']:g} "
                 "mm/min)")  # fmt: skip
    for a in LINEAR_AXES:
        if a in result.axes:
            r = result.axes[a]
            e = r.moves.loc[r.moves["compensate"], "predicted_error_um"].to_numpy()
            lines.append(f"  axis {a}, {result.settings.get('models', {}).get(a, r.model_name)} ({r.model_name}): "
                         f"{len(e)} G0/G1 moves revised, predicted error {e.min():+.2f} .. {e.max():+.2f} µm")  # fmt: skip
            v = result.verification.get(a)
            if v:
                lines.append(f"    verification ({v['moves']} move ends, original motion replayed): max |error| "
                             f"{v['max_abs_before_um']:.2f} -> {v['max_abs_after_um']:.2f} µm, RMS {v['rms_before_um']:.2f} "
                             f"-> {v['rms_after_um']:.2f} µm")  # fmt: skip
        elif a in result.as_written:
            lines.append(f"  axis {a}: as written ({result.as_written[a]})")
    lines += notes_and_passed_through(result.notes, result.unsupported, max_lines)
    return "\n".join(lines)
