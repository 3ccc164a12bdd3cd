"""Flatten a part program with LinuxCNC's standalone interpreter ``rs274``.

Real programs use what a line-by-line reader cannot follow: parameters and expressions
(``#<x>``, ``X[#1 + 2]``), loops and subroutines (``o100 repeat``, ``o<sub> call``), arcs.
``rs274 -g PROGRAM`` (Debian package ``linuxcnc-uspace``) runs LinuxCNC's own interpreter in
batch mode and prints the *canonical machining functions* it would send the motion
controller: ``STRAIGHT_TRAVERSE(x, y, z, a, b, c)``, ``STRAIGHT_FEED(...)``,
``ARC_FEED(...)``, ``DWELL(s)``, ``SET_FEED_RATE(f)``, spindle, coolant and tool calls.
:func:`flatten` writes them back as plain G-code, one block per canonical call.

**Only what the program commands.** rs274 assumes every axis starts at 0; the machine does not.
The program and the ``.ngc`` files beside it (its subroutines) are given to rs274 with each line
numbered (so each canonical call names the file and line it came from), and rs274 runs twice:
as the program is, and with the machine, its G28/G30 positions and its work offsets elsewhere.
A position that is the same in both runs is one the program's words set; one that differs is
where the interpreter only assumed the machine to be. So:

* ``STRAIGHT_TRAVERSE``/``STRAIGHT_FEED`` -> ``G0``/``G1`` with the axes the program has set, from
  the line that sets each on (``G0 X10 Y20`` with Z never named stays without Z; an axis it
  never names is never written); ``F`` when the feed changes; ``DWELL`` -> ``G4 P``; units as
  the interpreter had them (``G20``/``G21``); inverse-time feed (``G93``) arrives as the feed of
  each move;
* a return to the machine's G28/G30 position is written as ``G28``/``G30`` (``G91 G28 Z0 G90``
  for the axes the line names), a move in machine coordinates as ``G53 G0``/``G53 G1``, a tool
  length offset from the machine's table as the program's ``G43 H..``;
* a move to a position that depends on where the machine stands (an increment, an arc, a
  ``G10 L20`` before the axis has an absolute position; another coordinate system whose offset
  the machine's INI does not give) is refused in one line naming the file and line;
* ``ARC_FEED`` -> ``G1`` chords in its plane (G17/G18/G19), each deviating at most ``chord_tol``
  (program units) from the arc, the helix axis interpolated;
* offsets the program itself changes (G10 L2, G92, ...) are folded into the positions,
  relative to those at the start, so the flattened program runs under the same work offset;
  spindle, coolant, tool change, stops and comments are kept (``M3``/``M4``/``M5``, ``S``,
  ``M7``/``M8``/``M9``, ``T.. M6``, ``M0``/``M1``, ``M2``);
* a lathe program's diameter mode (``G7``): the interpreter gives radii, so the flattened program
  switches to ``G8`` where the original switched to ``G7``;
* anything else (probing, rotation of the XY plane, feed per revolution, spindle-synchronised
  motion, NURBS ...) is refused in one line naming the canonical call and the line;
* each move ends with a comment naming the line of the original it comes from (``(part.ngc:12)``).

The interpreter prints positions with 4 decimals in the program's units (0.1 µm in mm,
2.54 µm in inches): the flattened program carries that rounding. It is a different program
from the original (every loop unrolled, every arc in chords) that commands the same positions
on the axes the original commands: documented as such in its header.
"""

from __future__ import annotations

import contextlib
import math
import re
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import UserError

AXES = "XYZABC"
_PLANES = {"CANON_PLANE_XY": ("X", "Y", "Z", "G17"), "CANON_PLANE_XZ": ("Z", "X", "Y", "G18"),
           "CANON_PLANE_YZ": ("Y", "Z", "X", "G19")}  # fmt: skip
# canonical calls that change nothing the flattened program must carry
_QUIET = {"ON_RESET", "SET_FEED_REFERENCE", "SET_MOTION_CONTROL_MODE", "SET_NAIVECAM_TOLERANCE", "SET_SPINDLE_MODE",
          "ENABLE_FEED_OVERRIDE", "ENABLE_SPEED_OVERRIDE", "ENABLE_ADAPTIVE_FEED", "ENABLE_FEED_HOLD",
          "DISABLE_FEED_OVERRIDE", "DISABLE_SPEED_OVERRIDE", "DISABLE_ADAPTIVE_FEED", "DISABLE_FEED_HOLD",
          "SET_FEED_MODE", "START_CHANGE", "SET_TRAVERSE_RATE", "USE_NO_SPINDLE_FORCE", "SET_CUTTER_RADIUS_COMPENSATION",
          "START_CUTTER_RADIUS_COMPENSATION", "STOP_CUTTER_RADIUS_COMPENSATION", "TURN_PROBE_OFF", "TURN_PROBE_ON",
          "SELECT_POCKET", "SET_TOOL_TABLE_ENTRY", "UPDATE_TAG", "CHANGE_TOOL_NUMBER", "ORIENT_SPINDLE", "WAIT_SPINDLE_ORIENT_COMPLETE",
          "SPINDLE_RETRACT", "SPINDLE_RETRACT_TRAVERSE", "LOCK_SPINDLE_Z", "USE_SPINDLE_FORCE", "USE_SPINDLE_TORQUE", "CLAMP_AXIS",
          "UNCLAMP_AXIS", "NURB_KNOT_VECTOR", "PALLET_SHUTTLE", "SET_BLOCK_DELETE", "SET_OPTIONAL_PROGRAM_STOP", "FINISH"}  # fmt: skip
_SIMPLE = {"START_SPINDLE_CLOCKWISE": "M3", "START_SPINDLE_COUNTERCLOCKWISE": "M4", "STOP_SPINDLE_TURNING": "M5",
           "MIST_ON": "M7", "FLOOD_ON": "M8", "MIST_OFF": "M9", "FLOOD_OFF": "M9", "PROGRAM_STOP": "M0",
           "OPTIONAL_PROGRAM_STOP": "M1", "CHANGE_TOOL": "M6"}  # fmt: skip


class FlattenError(UserError):
    """The program cannot be flattened (rs274 refused it, or a canonical call has no plain
    G-code here); the message names the file and the reason."""


def rs274_path() -> str | None:
    """LinuxCNC's standalone interpreter, if installed."""
    return shutil.which("rs274")


@dataclass
class Flattened:
    text: str
    units: str  # "mm" or "inch": the program's units at its first move
    moves: int  # G0/G1 blocks written (arcs count per chord)
    arcs: int
    canonical_calls: int
    notes: list[str] = field(default_factory=list)
    origins: list[str | None] = field(default_factory=list)  # per line of text: file:line of the original (None)

    def origin(self, line: int) -> str | None:
        """``file:line`` of the original that line ``line`` (1-based) of the flattened text comes from."""
        return self.origins[line - 1] if 0 < line <= len(self.origins) else None


def _args(text: str) -> list[str]:
    return [a for a in re.split(r"[,\s]+", text.strip()) if a]


def _fmt(v: float, decimals: int = 4) -> str:
    s = f"{v:.{decimals}f}"
    return "0" if float(s) == 0 else s.rstrip("0").rstrip(".") if "." in s else s


#: a canonical call as ``rs274 -g`` prints it: sequence number, the block's N word (or dots), name, arguments
_CALL = re.compile(r"^\s*\d+\s+N(\d+|\.+)\s*([A-Z_0-9]+)\((.*)\)\s*$")
#: the N word thermbench gives line ``k`` of file ``i`` (0: the program; 1, 2, ...: the ``.ngc`` files beside it,
#: its subroutines): ``(i + 1) * LINE_BASE + k``, so each canonical call names the file and line it came from (a
#: smaller N is a user's own, in a file rs274 found elsewhere); PREAMBLE_N numbers the move to the other start
LINE_BASE = 1_000_000
PREAMBLE_N = LINE_BASE - 1
#: where the second run puts the machine before the program (and its G28/G30 positions): a position
#: that the program's own words do not depend on, so whatever differs between the runs was never set
_ELSEWHERE = dict(zip(AXES, (1357.9, -2468.1, 975.3, 111.1, 222.2, 333.3)))
#: the lengths among LinuxCNC's numbered parameters (X Y Z U V W of the G28 and G30 positions, the G92 offset
#: and the nine work offsets; A B C are angles)
_LENGTH_PARAMETERS = {base + k for base in (5161, 5181, 5211, *range(5221, 5382, 20)) for k in (0, 1, 2, 6, 7, 8)}
_SYSTEMS = {1: "G54", 2: "G55", 3: "G56", 4: "G57", 5: "G58", 6: "G59", 7: "G59.1", 8: "G59.2", 9: "G59.3"}
_PRINTED = 0.5e-4  # half the last of the 4 decimals rs274 prints: a smaller change of a set axis is no move
_TOL = 1e-6  # positions are printed with 4 decimals: equal in both runs means equal to this
#: an axis the program has not placed "moves" when it changes by more than this (mm, inch): rs274 prints
#: 4 decimals in the program's units, so a position printed in inches and then in mm differs by up to 1.3 µm
_MOVED = {"mm": 2e-3, "inch": 1.5e-4}


@dataclass
class Source:
    """The program's files as rs274 is given them: each line numbered (``N`` = file index x
    :data:`LINE_BASE` + line), so each canonical call names its file and line."""

    files: list[Path]  # index -> the user's file
    lines: list[list[str]]  # index -> its lines

    def _file(self, n: int | None) -> int | None:
        i = None if n is None else n // LINE_BASE - 1
        return i if i is not None and 0 <= i < len(self.files) else None

    def where(self, n: int | None) -> str:
        """``file:line`` of the block numbered ``n`` (the program's own name for its lines)."""
        i = self._file(n)
        if i is None:
            return "a block of a file outside the program's directory (a subroutine on the INI's path)"
        return f"{self.files[i].name}:{n % LINE_BASE}"

    def text(self, n: int | None) -> str:
        """The line numbered ``n`` as the user wrote it ("" when not one of the numbered files)."""
        i = self._file(n)
        lines = self.lines[i] if i is not None else []
        k = (n or 0) % LINE_BASE
        return lines[k - 1].strip() if 0 < k <= len(lines) else ""


def _numbered(lines: list[str], index: int) -> list[str]:
    """The lines with thermbench's ``N`` word first (after a block-delete ``/``; a line number of the
    user's own is replaced); blank and ``%`` lines as they are."""
    out = []
    for k, line in enumerate(lines, 1):
        body = line.strip()
        if not body or body.startswith("%"):
            out.append(line)
            continue
        slash = ""
        if body.startswith("/"):
            slash, body = "/", body[1:].lstrip()
        body = re.sub(r"^[Nn]\s*\d+\s*", "", body)
        out.append(f"{slash}N{(index + 1) * LINE_BASE + k} {body}")
    return out


_BLOCK_WORD = re.compile(r"([A-Za-z@^])\s*([-+]?\s*(?:\d+\.?\d*|\.\d+)|\[|#)")


def block_words(block: str) -> list[tuple[str, str]]:
    """(letter, value as written) of the words of a G-code block at its top level: outside comments,
    expressions in brackets and parameter names; an O-code line (``o100 repeat``) has none. A value
    that is an expression (``X[#1 + 2]``) or a parameter (``X#1``) reads ``[`` or ``#``."""
    code = re.sub(r"\([^)]*\)", " ", block.split(";", 1)[0])
    code = re.sub(r"<[^>]*>", "<>", code)
    code = re.sub(r"^\s*/?\s*[Nn]\s*\d+", "", code).strip()
    if code[:1] and code[:1] in "oO":
        return []
    out, depth = [], 0
    i = 0
    while i < len(code):
        ch = code[i]
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
        elif depth == 0 and (ch.isalpha() or ch in "@^"):
            m = _BLOCK_WORD.match(code, i)
            if m:
                out.append((m.group(1).upper(), m.group(2).replace(" ", "")))
                i = m.end() if m.group(2) not in ("[", "#") else m.end() - (m.group(2) == "[")
                continue
        i += 1
    return out


def _prepare(program: Path, tmp: Path, elsewhere: bool) -> tuple[Path, Source]:
    """The numbered copies of ``program`` and of the ``.ngc`` files beside it (its subroutines) in
    ``tmp``; ``elsewhere``: the program starts with a move of every axis to :data:`_ELSEWHERE`
    (machine coordinates, numbered :data:`PREAMBLE_N`; no motion mode left active)."""
    files = [program] + sorted(p for p in program.resolve().parent.iterdir()
                               if p.suffix.lower() == ".ngc" and p.is_file() and p.resolve() != program.resolve())  # fmt: skip
    texts = []
    for f in files:
        try:
            texts.append(f.read_text(encoding="utf-8", errors="replace").splitlines())
        except OSError as exc:
            raise FlattenError(f"{f}: cannot read it ({exc.strerror or exc})") from None
    for idx, (f, lines) in enumerate(zip(files, texts)):
        out = _numbered(lines, idx)
        if idx == 0 and elsewhere:
            first = next((k for k, ln in enumerate(out) if ln.strip()), 0)
            at = first + 1 if out and out[first].strip().startswith("%") else first
            out[at:at] = [f"N{PREAMBLE_N} G53 G0 " + " ".join(f"{a}{v}" for a, v in _ELSEWHERE.items()), f"N{PREAMBLE_N} G80"]
        (tmp / ("program.ngc" if idx == 0 else f.name)).write_text("\n".join(out) + "\n", encoding="utf-8")
    return tmp / "program.ngc", Source(files, texts)


def _var_file(path: Path, ini: Path | None, elsewhere: bool) -> Path:
    """rs274's parameter file in the scratch directory (rs274 rewrites it at the program's end): the
    INI's own ``PARAMETER_FILE`` copied when there is one; with ``elsewhere``, G28 and G30 positions
    at :data:`_ELSEWHERE` and every work offset shifted (a move to a home position or in machine
    coordinates must not count as set by the program's words), each coordinate system by its own
    amount unless the INI's parameter file gives the machine's offsets (without them, where G55 is
    relative to G54 is not known)."""
    params: dict[int, str] = {}
    if ini is not None:
        conf = Path(ini).read_text(encoding="utf-8", errors="replace")
        m = re.search(r"^\s*PARAMETER_FILE\s*=\s*(\S+)", conf, re.M)
        src = (Path(ini).parent / m.group(1)) if m else None
        if src is not None and src.is_file():
            units = re.search(r"^\s*LINEAR_UNITS\s*=\s*(\S+)", conf, re.M)
            # rs274 run on its own reads lengths in the parameter file as inches; a metric machine's are mm
            scale = 1 / 25.4 if units and units.group(1).lower() in ("mm", "metric", "millimeter", "millimeters") else 1.0
            for ln in src.read_text(encoding="utf-8", errors="replace").splitlines():
                f = ln.split()
                if len(f) >= 2 and f[0].isdigit():
                    key = int(f[0])
                    value = float(f[1]) * (scale if key in _LENGTH_PARAMETERS else 1.0)
                    params[key] = f"{key}\t{value!r}"
    text = "".join(params[k] + "\n" for k in sorted(params))
    if elsewhere:
        for base in (5161, 5181):  # the G28 and G30 positions
            for k, v in enumerate(_ELSEWHERE.values()):
                params[base + k] = f"{base + k}\t{v}"
        own = bool(text)  # the machine's own offsets: G55 ... relative to G54 are known, shift them alike
        for system in range(9):  # the work offsets G54 ... G59.3
            for k in range(len(AXES)):
                key = 5221 + 20 * system + k
                was = float(params[key].split()[1]) if key in params else 0.0
                params[key] = f"{key}\t{was + 37.3 * (1 if own else system + 1) + 3.1 * (k + 1)}"
        text = "\n".join(params[k] for k in sorted(params)) + "\n"
    path.write_text(text, encoding="utf-8")
    return path


_ATTEMPTS = 3


@contextlib.contextmanager
def _one_at_a_time():
    """rs274 runs one at a time on this machine: two at once can kill each other (SIGBUS). A lock file
    in the temporary directory (opened to append, never changed); without access to it, no lock."""
    import fcntl
    import tempfile

    try:
        fh = open(Path(tempfile.gettempdir()) / "thermbench-rs274.lock", "a")  # noqa: SIM115
    except OSError:
        yield
        return
    with fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def run_rs274(program: Path, tool_table: Path | None = None, timeout_s: float = 120.0, ini: Path | None = None,
              elsewhere: bool = False) -> tuple[list[tuple[str, list[str], int | None]], Source]:  # fmt: skip
    """The canonical calls of ``program`` (name, arguments, the block number: :class:`Source`), from
    ``rs274 -g`` run on numbered copies of it and of the ``.ngc`` files beside it (its subroutines)
    in a scratch directory, with ``tool_table`` (LinuxCNC's format; None: tools 1..99 with no
    offsets, as LinuxCNC's sim configurations have) and ``ini`` (the machine's INI; None: none).
    ``elsewhere``: the machine starts at :data:`_ELSEWHERE` (:func:`flatten` compares). rs274
    refusing a block is a :class:`FlattenError` naming the file and line."""
    import tempfile

    exe = rs274_path()
    if exe is None:
        raise FlattenError(f"{program}: flattening needs LinuxCNC's rs274 (Debian: apt-get install --no-install-recommends "
                           "linuxcnc-uspace)")  # fmt: skip
    if ini is not None and not Path(ini).is_file():
        raise FlattenError(f"{ini}: no such INI file (--ini: the machine's LinuxCNC configuration)")
    with tempfile.TemporaryDirectory(prefix="thermbench-rs274-") as tmp:
        tmp = Path(tmp)
        numbered, source = _prepare(program, tmp, elsewhere)
        if tool_table is None:
            tool_table = tmp / "tools.tbl"
            tool_table.write_text("".join(f"T{i} P{i} D0 Z0 ;\n" for i in range(1, 100)))
        cmd = [exe, "-t", str(Path(tool_table).resolve()), "-v", str(_var_file(tmp / "params.var", ini, elsewhere))]
        cmd += ["-i", str(Path(ini).resolve())] if ini is not None else []
        for attempt in range(_ATTEMPTS):
            try:
                with _one_at_a_time():
                    proc = subprocess.run([*cmd, "-g", str(numbered)], cwd=tmp, capture_output=True, text=True,
                                          stdin=subprocess.DEVNULL, timeout=timeout_s)  # fmt: skip
            except subprocess.TimeoutExpired:
                raise FlattenError(f"{program}: LinuxCNC's rs274 did not finish within {timeout_s:g} s (an endless "
                                   "loop?)") from None  # fmt: skip
            if proc.returncode >= 0:
                break
            # killed by a signal (SIGBUS when rs274 runs beside another rs274: measured 1 run in 3 with 6 at
            # once, so they take turns; a LinuxCNC of someone else's may still clash): its output is cut short
        else:
            raise FlattenError(f"{program}: LinuxCNC's rs274 was killed by signal {-proc.returncode} in each of "
                               f"{_ATTEMPTS} runs; expected it to finish (is another LinuxCNC running?)")  # fmt: skip
    calls, problems = [], []
    for line in proc.stdout.splitlines():
        m = _CALL.match(line)
        if m:
            n = int(m.group(1)) if m.group(1).isdigit() else None
            name = m.group(2)
            calls.append((name, _args(m.group(3)) if name not in ("COMMENT", "MESSAGE") else [m.group(3)], n))
        elif line.strip() and line.strip() != "executing":
            problems.append(line.strip())
    problems += [ln.strip() for ln in proc.stderr.splitlines() if ln.strip() and ln.strip() != "executing"]
    if problems:
        raise FlattenError(_refusal(program, source, problems))
    return calls, source


def _refusal(program: Path, source: Source, problems: list[str]) -> str:
    """rs274's refusal in one line: the user's file and line (rs274 echoes the numbered block after
    its message), the message, the line as the user wrote it."""
    block = next((p for p in problems if re.match(r"^/?N\d+\b", p)), None)
    said = [p for p in problems if p != block][:2]
    why = " / ".join(said) or "no reason given"
    if re.search(r"Bad character '[uvw]'", why, re.I):
        why += " (rs274 run on its own knows the axes X Y Z A B C only)"
    if block is None:
        return f"{program}: LinuxCNC's rs274 refused it: {why}"
    n = int(re.match(r"^/?N(\d+)", block).group(1))
    if source.text(n) == "":  # a block of a file rs274 found elsewhere: as rs274 echoed it
        return f"{program}: LinuxCNC's rs274 refused the block {block!r} ({source.where(n)}): {why}"
    return f"{program.parent / source.where(n)}: LinuxCNC's rs274 refused the line {source.text(n)!r}: {why}"


def flatten(program: str | Path, chord_tol: float | None = None, tool_table: Path | None = None,
            ini: Path | None = None) -> Flattened:  # fmt: skip
    """``program`` as plain G-code (module docstring). ``chord_tol``: the largest distance of an
    arc's chords from the arc, in program units (default 0.001 mm, 0.00004 inch). ``ini``: the
    machine's LinuxCNC INI for rs274 (subroutine paths, parameter file).

    rs274 runs twice: as the program is, and with the machine elsewhere at the start (and its
    G28/G30 positions and work offsets elsewhere). A position that is the same in both runs is one the program sets;
    one that differs depends on where the machine stands, which the interpreter only assumes. Such
    an axis is not written until the program sets it (a line ``G0 X10`` stays without Y and Z, and
    an axis the program never names is never written); a move that takes it somewhere the program
    does not set is a G28/G30 return (written as one) or refused in one line."""
    program = Path(program)
    calls, source = run_rs274(program, tool_table, ini=ini)
    other, _ = run_rs274(program, tool_table, ini=ini, elsewhere=True)
    elsewhere = [c for c in other if c[2] == PREAMBLE_N and c[0] == "STRAIGHT_TRAVERSE"]  # the move to the other start
    other = [c for c in other if c[2] != PREAMBLE_N]
    if not elsewhere:  # rs274 stopped before the first line (a program that is one '%' block of nothing)
        raise FlattenError(f"{program}: LinuxCNC's interpreter runs no line of it; expected a G-code program")
    if [c[0] for c in calls] != [c[0] for c in other]:
        raise FlattenError(f"{program}: the interpreter takes another path through it when the machine starts elsewhere "
                           "(it reads the position, #5420-#5428, or a G28/G30 position): its moves depend on where the "
                           "machine stands; expected a program whose motion its own words set")  # fmt: skip
    units = "mm"
    out = [f"( flattened by thermbench from {program.name} with LinuxCNC's rs274: parameters, expressions, loops, )",
           "( subroutines and arcs expanded into straight moves; an axis is written from the line that sets it on; )",
           "( each move names the line of the original it comes from )"]  # fmt: skip
    lines_from: list[int | None] = [None] * len(out)
    # per run (0: as the program is, 1: the machine elsewhere): position and offsets as the interpreter has them
    pos = [dict.fromkeys(AXES, 0.0), dict(zip(AXES, (float(v) for v in elsewhere[-1][1][:6])))]
    g5x = [dict.fromkeys(AXES, 0.0), dict.fromkeys(AXES, 0.0)]
    g92 = [dict.fromkeys(AXES, 0.0), dict.fromkeys(AXES, 0.0)]
    start: list[dict[str, float] | None] = [None, None]
    system = 1  # the coordinate system in use (1: G54 ... 9: G59.3)
    system_at_start = 1
    feed: float | None = None
    written_feed: float | None = None
    plane = "CANON_PLANE_XY"
    moves = arcs = 0
    first_units: str | None = None
    started = False  # the first ON_RESET block is the interpreter's start-up, before the program

    move_lines: set[int] = set()  # the lines of out that move

    def emit(text: str, n: int | None, moving: bool = False) -> None:
        if moving:
            move_lines.add(len(out))
        out.append(text)
        lines_from.append(n)

    def program_xyz(r: int, target: dict[str, float]) -> dict[str, float]:
        """Run ``r``'s canonical position as a position of the program under its starting offsets."""
        return {a: v + g5x[r][a] + g92[r][a] - (start[r] or {}).get(a, 0.0) for a, v in target.items()}

    def move(code: str, targets: tuple[dict[str, float], dict[str, float]], n: int | None) -> None:
        nonlocal moves, written_feed, first_units
        first_units = first_units or units
        before = [program_xyz(r, pos[r]) for r in (0, 1)]
        after = [program_xyz(r, targets[r]) for r in (0, 1)]
        set_ = {a for a in AXES if abs(after[0][a] - after[1][a]) <= _TOL}
        unset_moving = [a for a in AXES if a not in set_
                        and (abs(after[0][a] - before[0][a]) > _MOVED[units] or abs(after[1][a] - before[1][a]) > _MOVED[units])]  # fmt: skip
        pos[0].update(targets[0])
        pos[1].update(targets[1])
        if all(abs(after[r][a] - before[r][a]) <= (_PRINTED if a in set_ else _MOVED[units]) for r in (0, 1) for a in AXES):
            return  # a move to where the machine is (a G28's intermediate point at the current position)
        if unset_moving:
            said = block_words(source.text(n))
            words = dict(said)
            gs = {float(v) for k, v in said if k == "G" and v not in ("[", "#")}
            home = next((g for g in (28.0, 30.0) if g in gs), None)
            if code == "G0" and home is not None:  # the return to the machine's own G28/G30 position
                named = [a for a in AXES if a in words]
                emit(f"G91 G{home:g} " + " ".join(f"{a}0" for a in named) + " G90" if named else f"G{home:g}", n, True)
                moves += 1
                return
            machine = [{a: targets[r][a] + g5x[r][a] + g92[r][a] for a in AXES} for r in (0, 1)]
            if 53.0 in gs and all(abs(machine[0][a] - machine[1][a]) <= _TOL for a in unset_moving):
                # a move in machine coordinates: written as one, the axes the line names
                emit(f"G53 {code} " + " ".join(f"{a}{_fmt(machine[0][a])}" for a in AXES if a in words), n, True)
                moves += 1
                return
            if system != system_at_start:
                raise FlattenError(f"{program.parent / source.where(n)}: {source.text(n)!r} moves in coordinate system "
                                   f"{_SYSTEMS[system]}, whose offset from {_SYSTEMS[system_at_start]} (where the "
                                   "program starts) is the machine's; expected --ini naming the machine's INI (its "
                                   "PARAMETER_FILE holds the offsets), or one coordinate system")  # fmt: skip
            axes = ", ".join(unset_moving)
            raise FlattenError(f"{program.parent / source.where(n)}: {source.text(n)!r} moves {axes} to a position that "
                               "depends on where the machine stands (an increment, an arc or a G10 L20 before any absolute "
                               f"{unset_moving[0]} position); expected an absolute {unset_moving[0]} position (G90) first")  # fmt: skip
        words = [f"{a}{_fmt(after[0][a])}" for a in AXES if a in set_]
        if not words:  # nothing the program sets moves (an increment of 0 on an axis it never placed)
            return
        if code == "G1":
            if feed is None or feed <= 0:
                raise FlattenError(f"{program}: a feed move before any feed rate (SET_FEED_RATE)")
            if feed != written_feed:
                words.append(f"F{_fmt(feed)}")
                written_feed = feed
        emit(f"{code} " + " ".join(words), n, True)
        moves += 1

    for (name, args, n), (_, args1, _) in zip(calls, other):
        if name == "USE_LENGTH_UNITS":
            new_units = "inch" if "INCH" in args[0] else "mm"
            if new_units != units:  # the interpreter prints positions and offsets in the new units from here on
                k = 1 / 25.4 if new_units == "inch" else 25.4
                for table in (*pos, *g5x, *g92, *(st for st in start if st is not None)):
                    table.update({a: table[a] * k for a in "XYZ"})
            units = new_units
            if started:
                emit("G20" if units == "inch" else "G21", n)
        elif name == "ON_RESET":
            if start[0] is None:
                system_at_start = system
            for r in (0, 1):
                if start[r] is None:
                    start[r] = {a: g5x[r][a] + g92[r][a] for a in AXES}
            started = True
            emit("G20" if units == "inch" else "G21", n)
            emit("G90 G94", n)
        elif name == "SET_G5X_OFFSET":
            system = int(args[0])
            g5x[0].update(zip(AXES, (float(v) for v in args[1:7])))
            g5x[1].update(zip(AXES, (float(v) for v in args1[1:7])))
        elif name == "SET_G92_OFFSET":
            g92[0].update(zip(AXES, (float(v) for v in args[:6])))
            g92[1].update(zip(AXES, (float(v) for v in args1[:6])))
        elif name == "SET_XY_ROTATION":
            if float(args[0]) != 0.0:
                raise FlattenError(f"{program.parent / source.where(n)}: the program rotates the XY plane (G10 L2 "
                                   f"R{args[0]}); expected no rotation")  # fmt: skip
        elif name == "SET_FEED_RATE":
            feed = float(args[0])
        elif name == "SET_FEED_MODE" and len(args) > 1 and args[1] not in ("0",):
            raise FlattenError(f"{program.parent / source.where(n)}: feed per revolution (SET_FEED_MODE({', '.join(args)})); "
                               "expected feeds in units per minute (G94) or inverse time (G93)")  # fmt: skip
        elif name == "SELECT_PLANE":
            plane = args[0]
            if plane not in _PLANES:
                raise FlattenError(f"{program.parent / source.where(n)}: plane {plane} is not supported; expected G17, G18 or G19")
        elif name in ("STRAIGHT_TRAVERSE", "STRAIGHT_FEED"):
            move("G0" if name == "STRAIGHT_TRAVERSE" else "G1",
                 (dict(zip(AXES, (float(v) for v in args[:6]))), dict(zip(AXES, (float(v) for v in args1[:6])))), n)
        elif name == "ARC_FEED":
            arcs += 1
            tol = chord_tol or (0.00004 if units == "inch" else 0.001)
            ch0 = _chords(pos[0], plane, [float(v) for v in args], tol)
            ch1 = _chords(pos[1], plane, [float(v) for v in args1], tol, n=len(ch0))  # the same points where the program set them
            for t0, t1 in zip(ch0, ch1):
                move("G1", (t0, t1), n)
        elif name == "DWELL":
            emit(f"G4 P{_fmt(float(args[0]))}", n)
        elif name == "SET_SPINDLE_SPEED":
            emit(f"S{_fmt(float(args[-1]))}", n)
        elif name == "SELECT_TOOL":
            emit(f"T{int(float(args[0]))}", n)
        elif name in _SIMPLE:
            emit(_SIMPLE[name], n)
        elif name == "USE_TOOL_LENGTH_OFFSET":
            emit(_tool_length(args, block_words(source.text(n))), n)
        elif name == "COMMENT":
            text = args[0].strip().strip('"').replace("(", "[").replace(")", "]")
            emit(f"({text})", n)
            if "lathe diameter mode changed to diameter" in text.lower():
                # the interpreter halves X words under G7 before the canonical calls: its positions are radii, so the
                # flattened program says G8 (a lathe that starts in G7 would read them as diameters)
                emit("G8 (the positions below are radii: the interpreter has folded the diameter mode in)", n)
        elif name == "MESSAGE":
            emit(f"(MSG, {args[0].strip().strip(chr(34))})", n)
        elif name == "PROGRAM_END":
            emit("M2", n)
            break
        elif name in _QUIET or name == "SET_FEED_MODE":
            continue
        else:
            raise FlattenError(f"{program.parent / source.where(n)}: the interpreter's {name}({', '.join(args)}) has no "
                               "plain G-code in the flattened program; expected moves, dwells, spindle, coolant and tool "
                               "changes")  # fmt: skip
    if out[-1] != "M2":
        emit("M2", None)
    # each move names the line of the original it comes from (messages about the flattened program use it)
    text = [f"{ln} ({source.where(k)})" if k and i in move_lines else ln for i, (ln, k) in enumerate(zip(out, lines_from))]
    return Flattened("\n".join(text) + "\n", first_units or units, moves, arcs, len(calls),
                     origins=[source.where(k) if k else None for k in lines_from])


def _tool_length(args: list[str], words: list[tuple[str, str]]) -> str:
    """USE_TOOL_LENGTH_OFFSET as the block that set it: ``G43 H<n>`` (or ``G43``) stays itself, so the
    machine applies its own tool table, not the one rs274 was given; ``G49`` too; any other
    (``G43.1``, ``G43.2``) as the ``G43.1`` of the offsets the interpreter applied."""
    gs = {v for k, v in words if k == "G"}
    if {"43", "43.0"} & gs:
        h = next((v for k, v in words if k == "H"), None)
        return "G43" + (f" H{int(float(h))}" if h not in (None, "[", "#") else "")
    vals = dict(zip(AXES, (float(v) for v in args[:6])))
    nz = [f"{a}{_fmt(v)}" for a, v in vals.items() if v != 0.0]
    if "49" in gs or not nz:
        return "G49"
    return "G43.1 " + " ".join(nz)


def _chords(pos: dict[str, float], plane: str, a: list[float], tol: float, n: int | None = None) -> list[dict[str, float]]:
    """ARC_FEED(first_end, second_end, first_centre, second_centre, rotation, axis_end, a, b, c, ...)
    as chord end points: ``rotation`` > 0 counter-clockwise (G3), < 0 clockwise (G2); |rotation| > 1
    adds full turns. ``n``: this many chords (default: as few as keep them within ``tol``)."""
    p1, p2, pn, _ = _PLANES[plane]
    e1, e2, c1, c2, rot, en = a[:6]
    r0 = math.hypot(pos[p1] - c1, pos[p2] - c2)
    r1 = math.hypot(e1 - c1, e2 - c2)
    t0 = math.atan2(pos[p2] - c2, pos[p1] - c1)
    t1 = math.atan2(e2 - c2, e1 - c1)
    turns = abs(int(rot)) - 1
    full = abs(e1 - pos[p1]) < 1e-12 and abs(e2 - pos[p2]) < 1e-12  # start = end: a whole circle
    if rot > 0:
        sweep = 2 * math.pi if full else (t1 - t0) % (2 * math.pi)
        sweep += 2 * math.pi * turns
    else:
        sweep = -(2 * math.pi if full else (t0 - t1) % (2 * math.pi))
        sweep -= 2 * math.pi * turns
    r = max(r0, r1, 1e-12)
    step = 2 * math.acos(max(-1.0, 1 - tol / r)) if tol < r else math.pi / 2
    n = n or max(1, math.ceil(abs(sweep) / max(step, 1e-6)))
    rest = dict(zip("ABC", a[6:9]))
    pts = []
    for i in range(1, n + 1):
        f = i / n
        t = t0 + sweep * f
        rr = r0 + (r1 - r0) * f
        p = {p1: c1 + rr * math.cos(t), p2: c2 + rr * math.sin(t), pn: pos[pn] + (en - pos[pn]) * f}
        p.update({k: pos[k] + (v - pos[k]) * f for k, v in rest.items()})
        if i == n:
            p.update({p1: e1, p2: e2, pn: en})
        pts.append(p)
    return pts
