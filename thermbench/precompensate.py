"""Pre-compensation of a part program before machining (seed 003 §1).

Seed 003 compensates thermal errors "before machining" by revising the workpiece NC
program: the error is predicted "as soon as the workpiece NC machining program is
made", from the planned operation alone, with a model that needs no temperature
sensors. Here, for one feed axis:

1. :func:`parse_program` reads the G-code (G0/G1, G90/G91, F, G4 P<seconds>, G21,
   comments, N numbers, M codes); everything else passes through untouched and is
   listed with its line number and the reason;
2. :func:`plan_motion` times the program from feeds and distances and writes the
   planned process log (``t_s, axis_mm, feed_mm_min`` every ``sample_s``);
3. :func:`precompensate` predicts, with a fitted thermbench model that reads only
   the motion (:class:`~thermbench.models.physics.PhysicsModel`, the ambient held
   constant, or :class:`~thermbench.models.autoregressive.AutoRegressiveSeed003`),
   the thermal error each G0/G1 move meets at its end time at its target, and
   rewrites the target as ``target - error`` (incremental blocks get the increment
   that puts the axis on the compensated point);
4. :func:`verify_in_simulator` replays the original motion in the simulator
   (a :class:`~thermbench.sim.model.ScrewThermalModel` truth) and compares the
   error at every move end before and after.

:func:`run_precompensate` does it all from files; :func:`format_summary` prints it.
Every user mistake raises :class:`PrecompError` (a ``ValueError``) whose message
names the file, the line and what was expected. Full description:
docs/precompensate.md.
"""

from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from .outputs import check_output_file, write_text
from .data.dataset import Dataset
from .data.schema import FORMAT, Metadata
from .models.base import ModelError, ThermalErrorModel
from .sim.model import Motion, ScrewThermalModel

__all__ = [
    "Block",
    "PrecompError",
    "PrecompResult",
    "Program",
    "ProgramError",
    "Unsupported",
    "format_summary",
    "parse_program",
    "plan_motion",
    "planned_dataset",
    "precompensate",
    "predict_thermal_errors",
    "resolve_metadata",
    "run_precompensate",
    "simulate_true_errors",
    "truth_from_metadata",
    "verify_in_simulator",
]

RUN_ID = "program"
MOTION_COLUMNS = ("feed_mm_min", "axis_mm")  # what a planned program can supply


class PrecompError(ValueError):
    """A user mistake (program, model, dataset, option); the message says where and what was expected."""


class ProgramError(PrecompError):
    """The program cannot be read; the message names ``file:line``."""


# ------------------------------------------------------------------ reading ---
@dataclass
class Block:
    """One block that moves the axis or takes time (in program order).

    ``kind``: ``"G0"``, ``"G1"``, ``"G4"`` (dwell) or an unsupported motion that
    still moves the axis (``"G2"``, ``"G3"``, ``"G81"`` ...): its end point is
    followed and it is timed on the axis distance, but not compensated.
    Positions are program coordinates of the axis (mm; a G20 program's inches are converted). ``feed_mm_min`` is None
    for rapid moves (timed at the rapid feed of :func:`plan_motion`).
    ``span`` is where the axis word's number sits in the line (for the rewrite).
    """

    line: int  # 1-based line of the file
    kind: str
    start_mm: float
    target_mm: float
    feed_mm_min: float | None = None
    dwell_s: float = 0.0
    incremental: bool = False
    span: tuple[int, int] | None = None
    decimals: int = 0
    mm_per_unit: float = 1.0  # 25.4 under G20: the axis word and F are in inches (converted to mm here)

    @property
    def compensate(self) -> bool:
        return self.kind in ("G0", "G1")


@dataclass
class Unsupported:
    """A line passed through untouched whose content is (partly) not interpreted. ``origin``: for a
    flattened program, the line of the user's file it comes from (``part.ngc:12``)."""

    line: int
    text: str
    reason: str
    origin: str | None = None


@dataclass
class Program:
    """A parsed program: its lines (with their line endings), the blocks that move
    the axis or take time, and the lines with content that is not interpreted."""

    source: str
    axis: str
    lines: list[str]
    blocks: list[Block]
    unsupported: list[Unsupported]
    start_mm: float | None  # axis position before the first block (None: the first absolute target)


_WORD = re.compile(r"([A-Za-z])(\s*)([+-]?(?:\d+\.?\d*|\.\d+))")
_SILENT_M = {3, 4, 5, 7, 8, 9}  # spindle and coolant: no axis motion, no time
_END_M = {2, 30}
# non-modal codes after which the axis word is not a plain move target
_POSITION_CODES = {10: "G10", 28: "G28", 29: "G29", 30: "G30", 52: "G52", 53: "G53", 92: "G92"}


def _code_part(line: str, where: str) -> str:
    """The line with comments ``( ... )`` and ``; ...`` blanked (same length, so
    positions in it are positions in the line)."""
    out = []
    in_paren = False
    for i, ch in enumerate(line):
        if in_paren:
            out.append(" ")
            in_paren = ch != ")"
        elif ch == "(":
            out.append(" ")
            in_paren = True
        elif ch == ";":
            out.append(" " * (len(line) - i))
            break
        else:
            out.append(ch)
    if in_paren:
        raise ProgramError(f"{where}: unclosed '(' comment; expected ')' before the end of the line")
    return "".join(out)


def _split_lines(text: str) -> list[str]:
    """The lines of ``text`` with their endings (``\n`` or ``\r\n``) kept, split on
    ``\n`` only, so line numbers are those of any editor."""
    return re.findall(r"[^\n]*\n|[^\n]+$", text)


def _not_plain(rest: str) -> str:
    """What the line reader met where it expected a word (``rest``: the block from there): the name
    of the language feature it does not follow."""
    ch = rest[:1]
    if ch in "@^":
        return "polar coordinates @, ^"
    if ch == "#":
        return "parameters #"
    if ch == "[":
        return "expressions [...]"
    if ch in "oO":
        return "O-codes"
    if re.match(r"[A-Za-z]\s*[#\[]", rest):
        return "a word whose value is a parameter or an expression"
    return f"a character the reader does not know here: {rest[:12]!r}"


def _number(text: str) -> tuple[float, int]:
    """A word's value and its number of decimals as written."""
    return float(text), (len(text.split(".", 1)[1]) if "." in text else 0)


def _an(letter: str) -> str:
    """The article before a letter's name ("an X", "a Y")."""
    return "an" if letter.upper() in "AEFHILMNORSX" else "a"


def _gcode(value: float) -> str:
    return f"G{int(value)}" if value == int(value) else f"G{value:g}"


def parse_program(
    text: str, axis: str = "X", source: str = "<program>", start_mm: float | None = None,
    work_offset_mm: float | None = None,
) -> Program:
    """Read a G-code program for one feed axis (seed 003 §1: the planned operation).

    Supported: G0/G1 (modal), G90/G91 (modal, G90 at start), F (feed mm/min, modal),
    G4 dwell with ``P`` in seconds, G21 (mm) and G20 (inch: axis words and F read in inches and
    converted to mm, the rewrite written back in inches), G94, comments ``( ... )`` and ``;``,
    ``N`` numbers, ``%``, M codes (M2/M30 end the program: later lines pass through
    unread). Everything else passes through untouched and is listed in
    :attr:`Program.unsupported`; blocks that carry words of other axes only move no
    part of this axis and take no time (only G4 adds time). Arcs (G2/G3) and canned
    cycles that carry the axis word are followed to their end point, timed on the
    axis distance (at F or at the rapid feed) and not compensated.

    ``start_mm``: the axis position before the first block; None takes the first
    absolute target (so an incremental move before any absolute one is an error).
    ``work_offset_mm``: the axis position is the program coordinate plus this (:func:`plan_motion`);
    given, a ``G53 G0``/``G53 G1`` move in machine coordinates is followed to its end (program
    coordinate = machine - offset), timed and not compensated; None refuses it (the position after
    it is not known).
    Raises :class:`ProgramError` naming ``source:line`` for G93/G95,
    a G1 before any F, F <= 0, G4 without P, two axis words, an axis word with no
    G0/G1 in force or in a block the planner cannot follow (G28, G92, macros ...).
    """
    axis = str(axis).upper()
    if len(axis) != 1 or not axis.isalpha():
        raise PrecompError(f"axis: expected one letter (e.g. 'X'), got {axis!r}")
    lines = _split_lines(text)
    blocks: list[Block] = []
    unsupported: list[Unsupported] = []
    motion: str | None = None  # modal motion code in force
    incremental = False
    feed: float | None = None
    pos: float | None = None if start_mm is None else float(start_mm)
    ended = False
    mm_per_unit = 1.0  # G21 until a G20

    for number, raw in enumerate(lines, start=1):
        if ended:
            break
        line = raw.rstrip("\r\n")
        where = f"{source}:{number}"
        code = _code_part(line, where)
        words, junk = [], False
        block_delete = False
        i = 0
        while i < len(code):
            ch = code[i]
            if ch.isspace() or ch == "%":
                i += 1
            elif ch == "/" and not words:
                block_delete = True
                i += 1
            elif (m := _WORD.match(code, i)) is not None:
                value, decimals = _number(m.group(3))
                words.append((m.group(1).upper(), value, m.start(3), m.end(3), decimals))
                i = m.end()
            else:
                junk = _not_plain(code[i:])
                break
        if junk:
            if axis in code.upper():
                raise ProgramError(
                    f"{where}: {line.strip()!r} is not plain G-code words ({junk}) and mentions "
                    f"{axis}; the planner cannot follow the {axis} axis through it: expected '{axis}<number>'"
                )
            unsupported.append(Unsupported(number, line, f"not plain G-code words ({junk}): not interpreted"))
            continue

        reasons = ["block delete '/': interpreted as executed"] if block_delete else []
        axis_words = [w for w in words if w[0] == axis]
        if len(axis_words) > 1:
            raise ProgramError(f"{where}: {len(axis_words)} {axis} words in one block; expected at most one")
        new_motion: str | None = None
        motion_set = False
        dwell = False
        machine = False  # G53: this block's axis word is a machine coordinate
        for letter, value, *_ in words:
            if letter != "G":
                continue
            g = _gcode(value)
            if g in ("G0", "G1", "G2", "G3") or (value == int(value) and 73 <= value <= 89 and g != "G80"):
                if motion_set and new_motion != g:
                    raise ProgramError(f"{where}: two motion codes ({new_motion} and {g}) in one block; expected one")
                new_motion, motion_set = g, True
            elif g == "G80":
                new_motion, motion_set = None, True
            elif g == "G4":
                dwell = True
            elif g == "G20":  # inch: modal, and in force for this block's words too
                mm_per_unit = 25.4
            elif g == "G90":
                incremental = False
            elif g == "G91":
                incremental = True
            elif g == "G21":
                mm_per_unit = 1.0
            elif g in ("G94", "G8"):  # G8: lathe radius mode, the X words are positions
                pass
            elif g == "G7" and axis == "X":
                raise ProgramError(f"{where}: G7 (lathe diameter mode): its X words are diameters; expected a radius "
                                   "program (G8), or LinuxCNC's rs274 to flatten it (--flatten auto gives radii)")  # fmt: skip
            elif g == "G33":
                raise ProgramError(f"{where}: G33 (threading, F per revolution) is not supported; expected G0/G1 moves")
            elif g in ("G93", "G95"):
                raise ProgramError(
                    f"{where}: {g} (inverse-time / per-revolution feed) is not supported; expected G94 feeds in mm/min"
                )
            elif g == "G53" and axis_words and work_offset_mm is not None:
                machine = True
            elif value == int(value) and int(value) in _POSITION_CODES:
                if axis_words:
                    raise ProgramError(
                        f"{where}: {g} with {_an(axis)} {axis} word: the {axis} position after it is not known to the planner; "
                        f"expected a plain G0/G1 move (move {axis} explicitly before and after it)"
                    )
                reasons.append(f"{g} not interpreted ({axis} not involved)")
            else:
                reasons.append(f"{g} not interpreted")
        for letter, value, *_ in words:
            if letter == "F":
                if value <= 0:
                    raise ProgramError(f"{where}: feed F{value:g}; expected a feed > 0 in mm/min (inch/min under G20)")
                feed = value * mm_per_unit
            elif letter == "M":
                mv = int(value) if value == int(value) else value
                if mv in _END_M:
                    ended = True
                elif mv in (0, 1):
                    reasons.append(f"M{mv} program stop: the wait is not modelled (0 s)")
                elif mv == 6:
                    reasons.append("M6 tool change: its duration is not modelled")
                elif mv in (98, 99):
                    reasons.append(f"M{mv} subprogram call/return: the subprogram's motion is not modelled")
                elif mv not in _SILENT_M:
                    reasons.append(f"M{mv:g} not interpreted")
            elif letter == "T":
                reasons.append(f"T{value:g} tool selection: not modelled")

        if motion_set:
            motion = new_motion
        if dwell:
            if axis_words:
                raise ProgramError(
                    f"{where}: G4 with {_an(axis)} {axis} word; expected the dwell as P<seconds> ({_an(axis)} {axis} word there is "
                    f"a dwell time on some controls, not a move)"
                )
            p = [w[1] for w in words if w[0] == "P"]
            if not p or p[0] < 0:
                raise ProgramError(f"{where}: G4 without a valid dwell; expected P<seconds> >= 0 (e.g. G4 P2.5)")
            x = pos if pos is not None else math.nan
            blocks.append(Block(number, "G4", x, x, dwell_s=float(p[0])))
            p_text = next(line[w[2] : w[3]] for w in words if w[0] == "P")
            if "." not in p_text and p[0] >= 100:
                reasons.append(f"G4 P{p_text} read as {p[0]:g} s (P in seconds here; Fanuc-style controls read ms)")
        elif axis_words:
            _, value, s0, s1, decimals = axis_words[0]
            value *= mm_per_unit
            if motion is None:
                raise ProgramError(
                    f"{where}: {axis}{value:g} but no motion mode is in force; "
                    f"expected G0 or G1 on or before this block"
                )
            if incremental and pos is None:
                raise ProgramError(
                    f"{where}: incremental (G91) {axis} move before the {axis} position is known; expected an absolute "
                    f"(G90) move first, or give the start position (start_mm)"
                )
            if machine and motion not in ("G0", "G1"):
                raise ProgramError(f"{where}: G53 with {motion}; expected G0 or G1 (a move in machine coordinates)")
            target = value - float(work_offset_mm) if machine else pos + value if incremental else value
            start = pos if pos is not None else target
            rapid = motion not in ("G1", "G2", "G3")  # G0, and canned cycles position at rapid
            if not rapid and feed is None:
                raise ProgramError(
                    f"{where}: {motion} move with no feed in force; expected F<mm/min> on or before the first "
                    f"{motion} block"
                )
            blocks.append(
                Block(number, "G53" if machine else motion, start, target, None if rapid else feed, 0.0,
                      incremental and not machine, (s0, s1), decimals, mm_per_unit)
            )
            if machine:
                reasons.append(f"G53 {motion} with {axis}: a move in machine coordinates, followed to {axis}{value:g} - the "
                               f"work offset {float(work_offset_mm):g} mm, timed, not compensated")  # fmt: skip
            elif motion not in ("G0", "G1"):
                reasons.append(
                    f"{motion} with {axis}: end point followed, timed on the {axis} distance, not compensated"
                )
            pos = target
        elif motion not in (None, "G0", "G1") and any(w[0] in "XYZIJKR" for w in words):
            reasons.append(f"{motion} motion: not timed, not compensated")
        if reasons:
            unsupported.append(Unsupported(number, line, "; ".join(reasons)))

    # dwells before the first known position sit where the axis first goes
    first = next((b.start_mm for b in blocks if b.kind != "G4"), math.nan)
    for b in blocks:
        if b.kind == "G4" and math.isnan(b.start_mm):
            b.start_mm = b.target_mm = first
    return Program(source, axis, lines, blocks, unsupported, None if start_mm is None else float(start_mm))


# ------------------------------------------------------------------- timing ---
def _check_positive(name: str, value, upper: float | None = None) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise PrecompError(f"{name}: expected a number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0) or (upper is not None and v > upper):
        bound = f" and <= {upper:g}" if upper is not None else ""
        raise PrecompError(f"{name}: expected a finite number > 0{bound}, got {value!r}")
    return v


def _sample(t_w: np.ndarray, x_w: np.ndarray, feed_seg: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (linear within a segment) and feed (of the segment in force; 0 after
    the last one) at ``t_s`` of a piecewise-linear motion through waypoints."""
    x = np.interp(t_s, t_w, x_w)
    k = np.searchsorted(t_w, t_s, side="right") - 1
    f = np.where((k >= 0) & (k < feed_seg.size), feed_seg[np.clip(k, 0, max(feed_seg.size - 1, 0))], 0.0)
    return x, f


def _waypoints(moves: pd.DataFrame, start_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, axis position) at every segment end with the feed of each segment, from the moves table."""
    timed = moves[moves["duration_s"] > 0]
    x0 = float(moves["axis_start_mm"].iloc[0])
    t_w = np.r_[start_s, timed["t_end_s"].to_numpy()]
    x_w = np.r_[x0, timed["axis_target_mm"].to_numpy()]
    return t_w, x_w, timed["feed_mm_min"].to_numpy()


def plan_motion(
    program: Program,
    rapid_mm_min: float = 10000.0,
    sample_s: float = 1.0,
    start_s: float = 0.0,
    work_offset_mm: float = 0.0,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Time the program from feeds and distances (seed 003 §1: the planned operation).

    A move takes ``|Δ| / feed · 60`` s (G0 at ``rapid_mm_min``, and no feed faster: the rapid is the
    machine's top speed), a G4 its dwell;
    nothing else takes time (no acceleration, tool changes, other axes' motion).
    The clock starts at ``start_s`` with the axis cold. The axis position is the
    program coordinate plus ``work_offset_mm`` (the machine coordinate the model
    knows).

    Returns ``(moves, process)``: ``moves`` one row per block of
    :attr:`Program.blocks` (``line, kind, compensate, start_mm, target_mm,
    axis_start_mm, axis_target_mm, feed_mm_min, dwell_s, t_start_s, t_end_s,
    duration_s``; feed 0 at a dwell), ``process`` the planned process log
    (``t_s, axis_mm, feed_mm_min``) every ``sample_s`` and at the program end,
    position linear within a move, feed of the move in force (0 at a dwell and
    after the end).
    """
    rapid = _check_positive("rapid_mm_min", rapid_mm_min)
    sample = _check_positive("sample_s", sample_s, upper=1.0)  # the dataset contract: >= 1 sample per second
    try:
        t = float(start_s)
        offset = float(work_offset_mm)
    except (TypeError, ValueError):
        raise PrecompError(
            f"start_s and work_offset_mm: expected numbers, got {start_s!r}, {work_offset_mm!r}"
        ) from None
    if not (math.isfinite(t) and math.isfinite(offset)):
        raise PrecompError(f"start_s and work_offset_mm: expected finite numbers, got {start_s!r}, {work_offset_mm!r}")
    if not any(b.compensate for b in program.blocks):
        raise PrecompError(f"{program.source}: no G0/G1 move on axis {program.axis}; nothing to compensate")
    start_s = t
    rows = []
    for b in program.blocks:
        if b.kind == "G4":
            feed, duration = 0.0, b.dwell_s
        else:  # no feed is faster than the machine's rapid (LinuxCNC limits it to the axis's maximum velocity)
            feed = rapid if b.feed_mm_min is None else min(b.feed_mm_min, rapid)
            duration = abs(b.target_mm - b.start_mm) / feed * 60.0
        rows.append(
            {
                "line": b.line,
                "kind": b.kind,
                "compensate": b.compensate,
                "start_mm": b.start_mm,
                "target_mm": b.target_mm,
                "axis_start_mm": b.start_mm + offset,
                "axis_target_mm": b.target_mm + offset,
                "feed_mm_min": feed,
                "dwell_s": b.dwell_s,
                "t_start_s": t,
                "t_end_s": t + duration,
                "duration_s": duration,
            }
        )
        t += duration
    moves = pd.DataFrame(rows)
    if t - start_s <= 0:
        raise PrecompError(
            f"{program.source}: the program takes no time on axis {program.axis} (all moves are zero-length)"
        )
    t_w, x_w, f_seg = _waypoints(moves, start_s)
    grid = np.arange(start_s, t, sample)
    if t - grid[-1] > 1e-6:
        grid = np.append(grid, t)
    axis_mm, feed_mm_min = _sample(t_w, x_w, f_seg, grid)
    process = pd.DataFrame({"t_s": grid, "axis_mm": axis_mm, "feed_mm_min": feed_mm_min})
    return moves, process


# --------------------------------------------------------------- prediction ---
def resolve_metadata(source) -> Metadata:
    """The dataset metadata a model was trained with (machine, screw, material, sensors):
    from a :class:`Dataset`, a :class:`Metadata`, a dataset directory or a benchmark
    dataset name (``seed000_x`` ...; built on first use)."""
    from .data.io import DatasetError, load_metadata

    if isinstance(source, Dataset):
        return source.metadata
    if isinstance(source, Metadata):
        return source
    if isinstance(source, (str, Path)):
        path = Path(source)
        try:
            if path.is_dir():
                return load_metadata(path)
            from .bench import datasets

            if str(source) in datasets.names():
                where = datasets.default_root() / str(source)
                if not datasets.is_built(str(source)):
                    # a simulation that writes a directory: said before it starts (minutes, in the working directory)
                    print(f"precompensate: the model's training dataset {source} is not at {where}; simulating it there "
                          "for its machine's metadata (--dataset DIR names one you have; THERMBENCH_DATA moves the "
                          "benchmark datasets)", file=sys.stderr, flush=True)  # fmt: skip
                built, _ = datasets.build(str(source))
                return load_metadata(built)
        except DatasetError as exc:
            raise PrecompError(f"dataset {source}: {exc}") from None
        from .bench import datasets

        raise PrecompError(
            f"dataset {source!r}: not a dataset directory nor a benchmark dataset name; expected a directory "
            f"with metadata.yaml or one of {datasets.names()}"
        )
    raise PrecompError(
        f"dataset: expected a Dataset, Metadata, directory or benchmark name, got {type(source).__name__}"
    )


def _model_drive(model, metadata: Metadata) -> list[str]:
    """The ambient sensor(s) a model needs (held constant); an error when the model
    needs anything a planned program cannot supply (seed 003: no temperature sensors)."""
    if not isinstance(model, ThermalErrorModel):
        raise PrecompError(
            f"model: unsupported type {type(model).__module__}.{type(model).__name__}; expected a fitted thermbench "
            f"model that reads only the motion (PhysicsModel or AutoRegressiveSeed003)"
        )
    name = type(model).__name__
    try:
        inp = model.required_inputs()
    except ModelError as exc:
        raise PrecompError(f"model: {exc}") from None
    ambient = [s for s in inp.sensors if metadata.sensors.get(s) == "ambient"]
    if inp.ambient and not ambient and len(inp.sensors) == 1:
        ambient = list(inp.sensors)
    others = [s for s in inp.sensors if s not in ambient]
    if others:
        raise PrecompError(
            f"model: {name} needs temperature sensor(s) {others}, which a planned program cannot supply; expected "
            f"a model that reads only the motion (seed 003): physics (ambient held constant) or ar_seed003"
        )
    extra = [c for c in inp.operating if c not in MOTION_COLUMNS]
    if extra:
        raise PrecompError(
            f"model: {name} reads process column(s) {extra}; a planned program supplies only {list(MOTION_COLUMNS)}"
        )
    return ambient


def planned_dataset(
    metadata: Metadata,
    process: pd.DataFrame,
    ambient: dict[str, float] | None = None,
    run_id: str = RUN_ID,
    notes: str | None = None,
) -> Dataset:
    """A valid one-run :class:`Dataset` whose process log is the planned motion.

    The machine, screw and material are those of ``metadata`` (the training
    dataset's); the sensors are only ``ambient`` (name -> constant °C, a column
    ``<name>_C`` held at that value). The errors table holds one reading at the
    program start (error 0) so that the dataset meets the contract; the motion-driven
    models predict from the process log and the metadata only.
    """
    ambient = dict(ambient or {})
    pr = process[["t_s", "axis_mm", "feed_mm_min"]].astype(float).reset_index(drop=True)
    pr.insert(0, "run_id", run_id)
    for name, value in ambient.items():
        pr[f"{name}_C"] = float(value)
    lo, hi = float(pr["axis_mm"].min()), float(pr["axis_mm"].max())
    moving = pr.loc[pr["feed_mm_min"] > 0, "feed_mm_min"]
    meta = metadata.model_dump(mode="json", exclude_none=True)
    body = {
        "format": FORMAT,
        "machine": meta["machine"],
        "screw": meta["screw"],
        "material": meta["material"],
        "sensors": {s: metadata.sensors.get(s, "ambient") for s in ambient},
        "runs": {
            run_id: {
                "condition": {
                    "stroke_mm": hi - lo,
                    "start_mm": lo,
                    "end_mm": hi,
                    "feed_mm_min": float(moving.median()) if len(moving) else 0.0,
                },
                **({"notes": notes} if notes else {}),
            }
        },
    }
    errors = pd.DataFrame(
        {
            "run_id": [run_id],
            "t_s": [float(pr["t_s"].iloc[0])],
            "target_mm": [float(pr["axis_mm"].iloc[0])],
            "error_um": [0.0],
        }
    )
    return Dataset(Metadata.model_validate(body), pr, errors)


def predict_thermal_errors(
    model: ThermalErrorModel,
    metadata,
    process: pd.DataFrame,
    t_s,
    axis_mm,
    ambient_C: float = 20.0,
    notes: str | None = None,
) -> np.ndarray:
    """The model's thermal error (µm, measured - commanded) at (t, axis) pairs of the
    planned process log (:func:`planned_dataset` on the training dataset's
    ``metadata``), the ambient (if the model reads one) held at ``ambient_C``."""
    meta = resolve_metadata(metadata)
    ambient = _model_drive(model, meta)
    ds = planned_dataset(meta, process, {s: ambient_C for s in ambient}, notes=notes)
    try:
        e = model.predict_thermal_at(ds, RUN_ID, t_s, axis_mm)
    except ModelError as exc:
        raise PrecompError(f"model: {exc}") from None
    if not np.all(np.isfinite(e)):
        raise PrecompError(f"model: {type(model).__name__} predicted a non-finite error for the planned motion")
    return e


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
    from .sim.effects import effects_from_config
    from .sim.parts import CoreParams, Material, Numerics, Screw

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


# ------------------------------------------------------------------- files ---
def _read_program(path: Path) -> str:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise PrecompError(
            f"{path}: cannot read the program ({exc.strerror or exc}); expected a G-code text file"
        ) from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise PrecompError(f"{path}:{line}: not UTF-8/ASCII text; expected a G-code text file") from None


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
        from .bench import datasets

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
    from .linuxcnc.rs274 import flatten as rs274_flatten, rs274_path

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


def _flatten_reason(text: str, axis: str, source: str, start_mm, work_offset_mm=None) -> str | None:
    """Why the line reader cannot follow ``text`` alone (None: it can): its own refusal, or O-codes,
    parameters or expressions it passed over. (Arcs it follows, uncompensated: ``--flatten always``
    turns them into compensated chords.)"""
    try:
        prog = parse_program(text, axis, source, start_mm, work_offset_mm)
    except ProgramError as exc:
        return f"the reader refused it: {str(exc).split(': ', 1)[-1]}"
    kinds = dict.fromkeys(re.search(r"\((.*)\)", u.reason).group(1) for u in prog.unsupported
                          if u.reason.startswith("not plain G-code words ("))  # fmt: skip
    kinds.update(dict.fromkeys("M98/M99 subprograms" for u in prog.unsupported if "subprogram" in u.reason))
    return ", ".join(kinds) or None


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


def check_decimals(decimals) -> int:
    """``decimals`` as an integer >= 1, or the one-line error."""
    try:
        value = int(decimals)
    except (TypeError, ValueError):
        raise PrecompError(f"decimals: expected an integer >= 1, got {decimals!r}") from None
    if value < 1:
        raise PrecompError(f"decimals: expected an integer >= 1, got {decimals!r}")
    return value


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
