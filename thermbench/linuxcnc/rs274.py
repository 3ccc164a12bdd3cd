"""Flatten a part program with LinuxCNC's standalone interpreter ``rs274``.

Real programs use what a line-by-line reader cannot follow: parameters and expressions
(``#<x>``, ``X[#1 + 2]``), loops and subroutines (``o100 repeat``, ``o<sub> call``), arcs.
``rs274 -g PROGRAM`` (Debian package ``linuxcnc-uspace``) runs LinuxCNC's own interpreter in
batch mode and prints the *canonical machining functions* it would send the motion
controller: ``STRAIGHT_TRAVERSE(x, y, z, a, b, c)``, ``STRAIGHT_FEED(...)``,
``ARC_FEED(...)``, ``DWELL(s)``, ``SET_FEED_RATE(f)``, spindle, coolant and tool calls.
:func:`flatten` writes them back as plain G-code, one block per canonical call:

* ``STRAIGHT_TRAVERSE``/``STRAIGHT_FEED`` -> ``G0``/``G1`` with every axis word, ``F`` when the
  feed changes; ``DWELL`` -> ``G4 P``; units as the interpreter had them (``G20``/``G21``);
* ``ARC_FEED`` -> ``G1`` chords in its plane (G17/G18/G19), each deviating at most
  ``chord_tol`` (program units) from the arc, the helix axis interpolated;
* offsets the program itself changes (G10 L2, G92, ...) are folded into the positions,
  relative to those at the start, so the flattened program runs under the same work offset;
  tool length offsets become ``G43.1``; spindle, coolant, tool change, stops and comments are
  kept (``M3``/``M4``/``M5``, ``S``, ``M7``/``M8``/``M9``, ``T.. M6``, ``M0``/``M1``, ``M2``);
* anything else (probing, rotation of the XY plane, inverse-time feed ...) is refused in one
  line naming the canonical call.

The interpreter prints positions with 4 decimals in the program's units (0.1 µm in mm,
2.54 µm in inches): the flattened program carries that rounding. It is a different program
from the original (every loop unrolled, every arc in chords), equivalent in motion: documented
as such in its header.
"""

from __future__ import annotations

import math
import re
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import UserError

_CALL = re.compile(r"^\s*\d+\s+N\S*\s+([A-Z_0-9]+)\((.*)\)\s*$")
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


def _args(text: str) -> list[str]:
    return [a for a in re.split(r"[,\s]+", text.strip()) if a]


def _fmt(v: float, decimals: int = 4) -> str:
    s = f"{v:.{decimals}f}"
    return "0" if float(s) == 0 else s.rstrip("0").rstrip(".") if "." in s else s


def run_rs274(program: Path, tool_table: Path | None = None, timeout_s: float = 120.0) -> list[tuple[str, list[str]]]:
    """The canonical calls of ``program`` (name, arguments), from ``rs274 -g`` run in the
    program's directory (where its subroutine files are), with ``tool_table`` (LinuxCNC's
    format; None: tools 1..99 with no offsets, as LinuxCNC's sim configurations have). rs274
    refusing a line is a :class:`FlattenError` quoting it."""
    import tempfile

    exe = rs274_path()
    if exe is None:
        raise FlattenError(f"{program}: flattening needs LinuxCNC's rs274 (Debian: apt-get install --no-install-recommends "
                           "linuxcnc-uspace)")  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="thermbench-rs274-") as tmp:
        if tool_table is None:
            tool_table = Path(tmp) / "tools.tbl"
            tool_table.write_text("".join(f"T{i} P{i} D0 Z0 ;\n" for i in range(1, 100)))
        cmd = [exe, "-t", str(Path(tool_table).resolve()), "-g", str(program.resolve())]
        try:
            proc = subprocess.run(cmd, cwd=program.resolve().parent, capture_output=True, text=True,
                                  stdin=subprocess.DEVNULL, timeout=timeout_s)  # fmt: skip
        except subprocess.TimeoutExpired:
            raise FlattenError(f"{program}: LinuxCNC's rs274 did not finish within {timeout_s:g} s (an endless loop?)") from None
    calls, problems = [], []
    for line in proc.stdout.splitlines():
        m = _CALL.match(line)
        if m:
            calls.append((m.group(1), _args(m.group(2)) if m.group(1) not in ("COMMENT", "MESSAGE") else [m.group(2)]))
        elif line.strip() and line.strip() != "executing":
            problems.append(line.strip())
    problems += [ln.strip() for ln in proc.stderr.splitlines() if ln.strip() and ln.strip() != "executing"]
    if problems:
        raise FlattenError(f"{program}: LinuxCNC's rs274 refused it: {' / '.join(problems[:3])}")
    return calls


def flatten(program: str | Path, chord_tol: float | None = None, tool_table: Path | None = None) -> Flattened:
    """``program`` as plain G-code (module docstring). ``chord_tol``: the largest distance of an
    arc's chords from the arc, in program units (default 0.001 mm, 0.00004 inch)."""
    program = Path(program)
    calls = run_rs274(program, tool_table)
    units = "mm"
    out = [f"( flattened by thermbench from {program.name} with LinuxCNC's rs274: parameters, expressions, loops, )",
           "( subroutines and arcs expanded into straight moves; positions as the interpreter printed them )"]  # fmt: skip
    pos = dict.fromkeys(AXES, 0.0)
    start_offset: dict[str, float] | None = None
    g5x = dict.fromkeys(AXES, 0.0)
    g92 = dict.fromkeys(AXES, 0.0)
    used: set[str] = set()
    feed: float | None = None
    written_feed: float | None = None
    plane = "CANON_PLANE_XY"
    moves = arcs = 0
    first_units: str | None = None
    started = False  # the first ON_RESET block is the interpreter's start-up, before the program

    def offset(axis: str) -> float:
        return g5x[axis] + g92[axis] - (start_offset or {}).get(axis, 0.0)

    def move(code: str, target: dict[str, float]) -> None:
        nonlocal moves, written_feed, first_units
        first_units = first_units or units
        for a, v in target.items():
            if abs(v - pos[a]) > 0 or a in "XYZ":
                used.add(a)
        pos.update(target)
        words = [f"{a}{_fmt(pos[a] + offset(a))}" for a in AXES if a in used]
        if code == "G1":
            if feed is None or feed <= 0:
                raise FlattenError(f"{program}: a feed move before any feed rate (SET_FEED_RATE)")
            if feed != written_feed:
                words.append(f"F{_fmt(feed)}")
                written_feed = feed
        out.append(f"{code} " + " ".join(words))
        moves += 1

    for name, args in calls:
        if name == "USE_LENGTH_UNITS":
            units = "inch" if "INCH" in args[0] else "mm"
            if started:
                out.append("G20" if units == "inch" else "G21")
        elif name == "ON_RESET":
            if start_offset is None:
                start_offset = {a: g5x[a] + g92[a] for a in AXES}
            started = True
            out.append("G20" if units == "inch" else "G21")
            out.append("G90 G94 G17")
        elif name == "SET_G5X_OFFSET":
            g5x.update(zip(AXES, (float(v) for v in args[1:7])))
        elif name == "SET_G92_OFFSET":
            g92.update(zip(AXES, (float(v) for v in args[:6])))
        elif name == "SET_XY_ROTATION":
            if float(args[0]) != 0.0:
                raise FlattenError(f"{program}: the program rotates the XY plane (G10 L2 R{args[0]}); expected no rotation")
        elif name == "SET_FEED_RATE":
            feed = float(args[0])
        elif name == "SET_FEED_MODE" and len(args) > 1 and args[1] not in ("0",):
            raise FlattenError(f"{program}: inverse-time or per-revolution feed (SET_FEED_MODE({', '.join(args)})); "
                               "expected feeds in units per minute (G94)")  # fmt: skip
        elif name == "SELECT_PLANE":
            plane = args[0]
            if plane not in _PLANES:
                raise FlattenError(f"{program}: plane {plane} is not supported; expected G17, G18 or G19")
            out.append(_PLANES[plane][3])
        elif name in ("STRAIGHT_TRAVERSE", "STRAIGHT_FEED"):
            move("G0" if name == "STRAIGHT_TRAVERSE" else "G1", dict(zip(AXES, (float(v) for v in args[:6]))))
        elif name == "ARC_FEED":
            arcs += 1
            for target in _chords(pos, plane, [float(v) for v in args], chord_tol or (0.00004 if units == "inch" else 0.001)):
                move("G1", target)
        elif name == "DWELL":
            out.append(f"G4 P{_fmt(float(args[0]))}")
        elif name == "SET_SPINDLE_SPEED":
            out.append(f"S{_fmt(float(args[-1]))}")
        elif name == "SELECT_TOOL":
            out.append(f"T{int(float(args[0]))}")
        elif name in _SIMPLE:
            out.append(_SIMPLE[name])
        elif name == "USE_TOOL_LENGTH_OFFSET":
            vals = dict(zip(AXES, (float(v) for v in args[:6])))
            nz = [f"{a}{_fmt(v)}" for a, v in vals.items() if v != 0.0]
            out.append("G43.1 " + " ".join(nz) if nz else "G49")
        elif name == "COMMENT":
            text = args[0].strip().strip('"').replace("(", "[").replace(")", "]")
            out.append(f"({text})")
        elif name == "MESSAGE":
            out.append(f"(MSG, {args[0].strip().strip(chr(34))})")
        elif name == "PROGRAM_END":
            out.append("M2")
            break
        elif name in _QUIET or name == "SET_FEED_MODE":
            continue
        else:
            raise FlattenError(f"{program}: the interpreter's {name}({', '.join(args)}) has no plain G-code in the "
                               "flattened program; expected moves, dwells, spindle, coolant and tool changes")  # fmt: skip
    if out[-1] != "M2":
        out.append("M2")
    return Flattened("\n".join(out) + "\n", first_units or units, moves, arcs, len(calls))


def _chords(pos: dict[str, float], plane: str, a: list[float], tol: float) -> list[dict[str, float]]:
    """ARC_FEED(first_end, second_end, first_centre, second_centre, rotation, axis_end, a, b, c, ...)
    as chord end points: ``rotation`` > 0 counter-clockwise (G3), < 0 clockwise (G2); |rotation| > 1
    adds full turns."""
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
    n = max(1, math.ceil(abs(sweep) / max(step, 1e-6)))
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
