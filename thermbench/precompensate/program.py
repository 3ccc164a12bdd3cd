"""Reading a part program (seed 003 §1): the G-code blocks thermbench can revise (G0/G1, G90/G91, F, G4
P<seconds>, G21, comments, N numbers, M codes) and everything else, passed through with its line
number and the reason (:func:`parse_program`); the errors a user's program or settings can raise.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path


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