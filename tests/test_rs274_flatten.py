"""Flattening part programs with LinuxCNC's interpreter (thermbench/linuxcnc/rs274.py) and
pre-compensating the result. LinuxCNC's ``rs274`` must be installed (``make test`` installs
``linuxcnc-uspace``): missing, these tests fail."""

from __future__ import annotations

import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from thermbench.linuxcnc.rs274 import FlattenError, flatten
from thermbench.precompensate import PrecompError, run_precompensate

PROGRAM = """( a loop, parameters, an expression, an arc: what the line reader cannot follow )
G21 G90 G94 G17
#<left> = 100
#<right> = [#<left> + 150]
G0 X#<left> Y0
F3000
o100 repeat [3]
  G1 X#<right>
  G1 X#<left>
o100 endrepeat
G2 X200 Y0 I50 J0
G4 P2.5
M2
"""


@pytest.fixture
def seed000_physics(tmp_path):
    """A physics model file equal to its truth, and the dataset directory naming that truth
    (as tests/test_precompensate.py makes them)."""
    import joblib
    import yaml

    from tests.test_precompensate import CoreParams, oracle, seed000_metadata

    sim = {"core": CoreParams().as_dict(), "effects": {}, "numerics": {"dx_m": 0.02, "dt_s": 0.5, "macro_dt_s": 10.0}}
    data = tmp_path / "data"
    data.mkdir()
    (data / "metadata.yaml").write_text(yaml.safe_dump(seed000_metadata(sim).model_dump(mode="json", exclude_none=True)))
    joblib.dump(oracle(), tmp_path / "physics.joblib")
    return tmp_path / "physics.joblib", data


@pytest.fixture(scope="module", autouse=True)
def rs274():
    assert shutil.which("rs274"), "LinuxCNC's rs274 is missing: apt-get install --no-install-recommends linuxcnc-uspace"


def _moves(text: str) -> list[tuple[str, float, float]]:
    out = []
    for line in text.splitlines():
        m = re.match(r"(G[01]) X(\S+) Y(\S+)", line)
        if m:
            out.append((m.group(1), float(m.group(2)), float(m.group(3))))
    return out


def test_flatten_expands_parameters_loops_and_arcs(tmp_path):
    p = tmp_path / "part.ngc"
    p.write_text(PROGRAM)
    f = flatten(p, chord_tol=0.001)
    mv = _moves(f.text)
    assert f.units == "mm" and f.arcs == 1
    # G0 to #<left> = 100, then the loop unrolled: 3 x (to 250, back to 100), every X by hand
    assert mv[0] == ("G0", 100.0, 0.0)
    assert [x for _, x, _ in mv[1:7]] == [250.0, 100.0] * 3 and all(k == "G1" for k, _, _ in mv[1:7])
    # G2 from (100, 0) to (200, 0) about (150, 0): a clockwise half circle of radius 50 over the top (y >= 0),
    # chords within 1 µm of the circle: the largest chord's sagitta r (1 - cos(d/2)) <= 0.001 mm
    arc = np.array([(x, y) for _, x, y in mv[7:]])
    assert tuple(arc[-1]) == (200.0, 0.0)
    r = np.hypot(arc[:, 0] - 150.0, arc[:, 1])
    assert np.all(np.abs(r - 50.0) <= 1e-4 + 1e-9)  # rs274 prints 4 decimals: the points are on the circle to 0.1 µm
    assert np.all(arc[:, 1] >= -1e-4) and arc[:, 1].max() == pytest.approx(50.0, abs=0.01)
    ang = np.unwrap(np.arctan2(arc[:, 1], arc[:, 0] - 150.0))
    step = np.abs(np.diff(np.concatenate([[math.pi], ang])))
    assert np.all(50.0 * (1 - np.cos(step / 2)) <= 0.001 + 1e-6) and len(arc) >= math.pi / (2 * math.acos(1 - 0.001 / 50))
    assert "G4 P2.5" in f.text and f.text.rstrip().endswith("M2") and "F3000" in f.text


def test_flatten_refuses_in_one_line(tmp_path):
    bad = tmp_path / "bad.ngc"
    bad.write_text("G21 G90\nG0 X[1 +]\nM2\n")
    with pytest.raises(FlattenError, match=r"bad.ngc:2: LinuxCNC's rs274 refused the line 'G0 X\[1 \+\]': ") as e:
        flatten(bad)
    assert "\n" not in str(e.value)
    probe = tmp_path / "probe.ngc"
    probe.write_text("G21 G90\nG0 X10 Z5\nG38.2 Z-10 F100\nM2\n")
    with pytest.raises(FlattenError, match=r"STRAIGHT_PROBE"):
        flatten(probe)


def test_precompensate_flattens_what_the_reader_refuses(tmp_path, seed000_physics):
    model, dataset = seed000_physics
    p = tmp_path / "part.ngc"
    p.write_text(PROGRAM)
    with pytest.raises(PrecompError, match="not plain G-code words"):
        run_precompensate(p, model, tmp_path / "never.ngc", dataset=dataset, flatten="never")
    res = run_precompensate(p, model, tmp_path / "auto.ngc", dataset=dataset, flatten="auto", truth="auto")
    assert res.settings["flattened"] and res.notes[0].startswith("flattened with LinuxCNC's rs274 (the reader refused it")
    comp = res.moves[res.moves["compensate"]]
    assert len(comp) == len(_moves(flatten(p).text))  # every straight move of the flattened program, arcs' chords too
    out = (tmp_path / "auto.ngc").read_text()
    assert out.startswith("( flattened by thermbench from part.ngc")
    # each written X is the flattened target minus the predicted error (µm -> mm)
    targets = np.array([x for _, x, _ in _moves(flatten(p).text)])
    written = np.array([x for _, x, _ in _moves(out)])
    np.testing.assert_allclose(written, targets - comp["predicted_error_um"].to_numpy() / 1000.0, atol=0.6e-4)
    v = res.verification
    assert v["moves"] == len(comp) and v["max_abs_after_um"] <= v["max_abs_before_um"]


# ------------------------------------------- no axis the original did not command ---
AXIS_LETTERS = "XYZABC"
NCFILES = Path("/usr/share/linuxcnc/ncfiles")  # the sample programs linuxcnc-uspace installs


def commanded(block: str) -> set[str]:
    """The axis letters a G-code block names, read here on its own (not with the flattener's reader):
    comments dropped, bracketed expressions collapsed, O-code lines name none; polar words (@, ^)
    name X and Y (the XY plane)."""
    code = re.sub(r"\([^)]*\)", "", block.split(";", 1)[0]).upper()
    code = re.sub(r"<[^>]*>", "", code)
    while "[" in code:
        collapsed = re.sub(r"\[[^\[\]]*\]", "0", code)
        if collapsed == code:
            break
        code = collapsed
    code = re.sub(r"^\s*/?\s*N\s*\d+", "", code).strip()
    if code.startswith("O"):
        return set()
    letters = set(re.findall(r"([A-Z@^])\s*[-+]?\s*[\d.#]", code))
    return (letters & set(AXIS_LETTERS)) | ({"X", "Y"} if letters & {"@", "^"} else set())


def flat_moves(text: str) -> list[tuple[str, dict[str, float], str | None]]:
    """(code, axis words, origin 'file:line') of each move of a flattened program."""
    out = []
    for line in text.splitlines():
        m = re.match(r"^(G5[3] G[01]|G9[01] G(?:28|30)[^(]*|G(?:28|30)|G[01])\s*(.*?)\s*(?:\(([^()]*)\))?$", line)
        if m:
            words = dict((a, float(v)) for a, v in re.findall(r"([XYZABC])(-?[\d.]+)", m.group(2)))
            out.append((m.group(1), words, m.group(3)))
    return out


def check_commanded(flat_text: str, sources: dict[str, list[str]]) -> list[str]:
    """Every axis word of a flattened program, checked against the original's lines: an axis is first
    written on a move whose line commands it; after that a written value either stays what it was
    (the position the original holds) or changes on a line that commands the axis, or on an arc, a
    canned cycle or a polar move (whose motion moves axes the line does not name). Returns the
    violations."""
    bad, last = [], {}
    for code, words, origin in flat_moves(flat_text):
        if origin is None:
            bad.append(f"a move without its origin: {code} {words}")
            continue
        name, line = origin.rsplit(":", 1)
        src = sources[name][int(line) - 1]
        named = commanded(src)
        modal = re.search(r"\b[Gg]\s*0*(2|3|73|8[1-9]|38\.\d)\b|[@^]", re.sub(r"\([^)]*\)", "", src)) is not None
        # a lathe cycle (G70-G72) reads its profile from an O-sub; rs274 numbers its moves with the profile's end
        # (and its last one with the next block): lines that name no axis
        modal |= not named and any(re.search(r"\bG7[0-2]\b", ln, re.I) for ln in sources[name])
        if code.startswith("G53") or "G28" in code or "G30" in code:
            assert set(words) <= named | {a for a in words if words[a] == 0.0}, (origin, src, code, words)
            last = {a: v for a, v in last.items() if a not in named} if named else {}
            continue
        for a, v in words.items():
            if a not in last and a not in named and not modal:
                bad.append(f"{origin} {src.strip()!r}: {a} written first as {a}{v:g}, not commanded there")
            elif a in last and abs(v - last[a]) > 1e-9 and a not in named and not modal:
                bad.append(f"{origin} {src.strip()!r}: {a} changed to {v:g} on a line that does not command it")
            last[a] = v
    return bad


def _sources(program: Path) -> dict[str, list[str]]:
    return {p.name: p.read_text(encoding="utf-8", errors="replace").splitlines()
            for p in program.parent.iterdir() if p.suffix.lower() == ".ngc"}  # fmt: skip


@pytest.mark.parametrize("program, first_moves", [
    # the case to get right: Z at a safe height the program never names before the XY traverse
    ("G21 G90\n#1=100\nG0 X#1 Y20\nG0 Z5\nG1 X10 F100\nM2\n",
     ["G0 X100 Y20", "G0 X100 Y20 Z5", "G1 X10 Y20 Z5 F100"]),
    # LinuxCNC's arcspiral.ngc opens with 'g0z1': Z clears first, X and Y stay where they are
    ("G20 G64\ng0z1\ng0x0y0z1\nM2\n", ["G0 Z1", "G0 X0 Y0 Z1"]),
    # Y first, then X, then Z: each from its own line on
    ("G21\nG0 Y5\nG0 X-3\nG1 Z-1 F50\nG1 X2\nM2\n", ["G0 Y5", "G0 X-3 Y5", "G1 X-3 Y5 Z-1 F50", "G1 X2 Y5 Z-1"]),
    # an axis commanded to where the interpreter assumes the machine is (0) is still a move: written
    ("G21\nG0 X0 Z0\nG0 Y0 A0\nM2\n", ["G0 X0 Z0", "G0 X0 Y0 Z0 A0"]),
])  # fmt: skip
def test_only_axes_the_program_commands_are_written(tmp_path, program, first_moves):
    p = tmp_path / "part.ngc"
    p.write_text(program)
    f = flatten(p)
    moves = [re.sub(r"\s*\(part\.ngc:\d+\)$", "", ln) for ln in f.text.splitlines() if re.match(r"^G[01] ", ln)]
    assert moves == first_moves
    assert check_commanded(f.text, {"part.ngc": program.splitlines()}) == []


def test_moves_to_where_the_program_does_not_say(tmp_path):
    p = tmp_path / "part.ngc"
    # a G28 return, a G91 G28 of Z alone, a move in machine coordinates: written as such, and the axes
    # they leave at positions the program does not set are not written again until it sets them
    p.write_text("G21 G90\nG0 X10 Y10 Z5\nG91 G28 Z0\nG90 G0 X1\nG28\nG0 Y2\nG53 G0 Z0\nG0 X3\nG0 Z4\nM2\n")
    text = flatten(p).text
    moves = [re.sub(r"\s*\(part\.ngc:\d+\)$", "", ln) for ln in text.splitlines() if re.match(r"^(G[01] |G53 |G91 G28|G28)", ln)]
    # after the G28 return no axis is at a position of the program's: Y2 alone, then X3 beside it
    assert moves == ["G0 X10 Y10 Z5", "G91 G28 Z0 G90", "G0 X1 Y10", "G28", "G0 Y2", "G53 G0 Z0", "G0 X3 Y2",
                     "G0 X3 Y2 Z4"]  # fmt: skip
    assert check_commanded(text, {"part.ngc": p.read_text().splitlines()}) == []
    # an increment from a position the program never set: refused, naming the line as the user wrote it
    p.write_text("G21 G90\nG0 X10\nG91 G1 Z-2 F100\nM2\n")
    with pytest.raises(FlattenError) as e:
        flatten(p)
    assert str(e.value) == (f"{p}:3: 'G91 G1 Z-2 F100' moves Z to a position that depends on where the machine stands "
                            "(an increment, an arc or a G10 L20 before any absolute Z position); expected an absolute "
                            "Z position (G90) first")  # fmt: skip
    # another coordinate system, whose offset the program does not give: refused, naming it
    p.write_text("G21 G90 G54\nG0 X10 Y0 Z5\nG55\nG0 X20\nM2\n")
    with pytest.raises(FlattenError, match=r"part\.ngc:4: 'G0 X20' moves in coordinate system G55, whose offset from G54"):
        flatten(p)
    # the tool length offset the machine applies from its own table: kept as the program wrote it
    p.write_text("G21 G90\nT1 M6\nG43 H1\nG0 X0 Y0 Z10\nG49\nM2\n")
    text = flatten(p).text
    assert "G43 H1" in text.splitlines() and "G49" in text.splitlines() and "G43.1" not in text


def test_a_refusal_names_the_users_line(tmp_path):
    p = tmp_path / "part.ngc"
    p.write_text("G21\n\n(a W axis, which rs274 run on its own does not have)\nG0 X1\nG1 W100 F2000 (drill)\nM2\n")
    with pytest.raises(FlattenError) as e:
        flatten(p)
    assert str(e.value) == (f"{p}:5: LinuxCNC's rs274 refused the line 'G1 W100 F2000 (drill)': Bad character 'w' used "
                            "(rs274 run on its own knows the axes X Y Z A B C only)")  # fmt: skip
    # a subroutine file beside the program: its own name and line
    (tmp_path / "sub.ngc").write_text("o<sub> sub\nG1 X[1 +] F10\no<sub> endsub\nM2\n")
    p.write_text("G21\nG0 X0 Y0 Z0\no<sub> call\nM2\n")
    with pytest.raises(FlattenError, match=r"sub\.ngc:2: LinuxCNC's rs274 refused the line 'G1 X\[1 \+\] F10'"):
        flatten(p)


def test_every_sample_program_writes_only_what_its_lines_command():
    """LinuxCNC's 56 sample programs: every one that flattens writes only axis words its own lines command
    (or the positions it already holds), and each move names its line."""
    programs = sorted(NCFILES.glob("*.ngc"))
    assert len(programs) == 56, f"expected LinuxCNC's 56 sample programs in {NCFILES}"
    flattened, problems = 0, {}
    for prog in programs:
        try:
            f = flatten(prog)
        except FlattenError as exc:
            assert "\n" not in str(exc) and re.match(rf"^{re.escape(str(prog.parent))}/[^:]+(:\d+)?: ", str(exc)), str(exc)
            continue
        flattened += 1
        bad = check_commanded(f.text, _sources(prog))
        if bad:
            problems[prog.name] = bad[:3]
    assert problems == {}
    assert flattened >= 40  # 42 with linuxcnc-uspace 2.9.0~pre1


def test_the_machines_ini_gives_the_work_offsets(tmp_path):
    """--ini: the machine's parameter file says where G55 is from G54 (a metric machine's lengths in mm)."""
    (tmp_path / "machine.ini").write_text("[RS274NGC]\nPARAMETER_FILE = machine.var\n[TRAJ]\nLINEAR_UNITS = mm\n")
    (tmp_path / "machine.var").write_text("5221\t1.5\n5241\t11.5\n5242\t-4\n")  # G54 X 1.5; G55 X 11.5, Y -4 (mm)
    p = tmp_path / "part.ngc"
    p.write_text("G21 G90 G54\nG0 X0 Y0 Z5\nG55\nG0 X20\nM2\n")
    with pytest.raises(FlattenError, match="coordinate system G55"):
        flatten(p)  # without the machine's offsets
    moves = [ln for ln in flatten(p, ini=tmp_path / "machine.ini").text.splitlines() if ln.startswith("G0 ")]
    # in G55, X20 is 10 mm further than in G54 (Y, not on the line, stays where it is)
    assert moves == ["G0 X0 Y0 Z5 (part.ngc:2)", "G0 X30 Y0 Z5 (part.ngc:4)"]
    assert (tmp_path / "machine.var").read_text() == "5221\t1.5\n5241\t11.5\n5242\t-4\n"  # rs274 wrote its own copy


def test_precompensate_says_why_it_flattened_and_where_each_line_came_from(tmp_path, seed000_physics):
    model, dataset = seed000_physics
    p = tmp_path / "holes.ngc"
    # LinuxCNC's hole-circle.ngc in mm: polar words, which the line reader does not follow
    p.write_text("G21 G17 G90\nT1 M6\nG0 X40 Y0 Z0\nG91 G81 R2 Z-12 ^60 L6 F250\nG90 G80\nM2\n")
    res = run_precompensate(p, model, tmp_path / "out.ngc", dataset=dataset)
    assert res.notes[0].startswith("flattened with LinuxCNC's rs274 (polar coordinates @, ^): ")
    # nothing of thermbench's own header is listed as not interpreted; what is listed names the user's line
    assert all("G17" not in u.text and "G94" not in u.text for u in res.unsupported)
    assert [(u.origin, u.reason) for u in res.unsupported if "M6" in u.reason] == [
        ("holes.ngc:2", "M6 tool change: its duration is not modelled")]
    assert all(u.origin and re.fullmatch(r"holes\.ngc:\d+", u.origin) for u in res.unsupported)
    from thermbench.precompensate import format_summary

    assert re.search(r"line \d+ \(from holes\.ngc:\d+\): ", format_summary(res))
    comp = res.moves[res.moves["compensate"]]
    assert len(comp) == 2 + 6 * 3  # the first move, up to the R plane, then per hole: to the hole, down, back up


def test_a_lathe_program_in_diameter_mode_is_flattened_to_radii(tmp_path, seed000_physics):
    """G7: the X words are diameters (X20 is 10 mm from the axis). The interpreter gives radii, so
    the flattened program says G8 and X10; pre-compensating every axis flattens it first (the
    reader refuses diameters), and without flattening the refusal is one line."""
    from thermbench.precompensate.axes import run_precompensate_axes

    prog = tmp_path / "lathe.ngc"
    prog.write_text("G18 G7 G21 G90\nG0 X20 Z5\nG1 X10 Z0 F100\nG1 X30 Z-40\nM2\n")
    flat = flatten(prog)
    moves = [tuple(float(v) for v in m) for m in re.findall(r"G[01] X(\S+) Z(\S+)", flat.text)]
    assert moves == [(10.0, 5.0), (5.0, 0.0), (15.0, -40.0)]  # by hand: half of each X word
    assert re.search(r"^G8\b", flat.text, re.M) and not re.search(r"^G7\b", flat.text, re.M)
    model, data = seed000_physics
    axes = tmp_path / "axes.yaml"
    axes.write_text(f"X: {{model: {model}, dataset: {data}}}\nZ: {{model: {model}, dataset: {data}}}\n")
    res = run_precompensate_axes(prog, axes, tmp_path / "out.ngc", verify=True)
    assert res.settings["flattened"] and "G7 (lathe diameter mode)" in res.notes[0]
    assert set(res.axes) == {"X", "Z"}
    np.testing.assert_allclose(res.axes["X"].moves.loc[res.axes["X"].moves["compensate"], "target_mm"], [10, 5, 15])
    assert all(v["max_abs_after_um"] < 0.5 for v in res.verification.values())
    with pytest.raises(PrecompError, match=r"lathe.ngc:1: G7 \(lathe diameter mode\)") as exc:
        run_precompensate_axes(prog, axes, tmp_path / "out2.ngc", flatten="never")
    assert "\n" not in str(exc.value) and not (tmp_path / "out2.ngc").exists()


def test_a_refusal_in_the_flattened_program_names_the_users_line(tmp_path, seed000_physics):
    """A G28 on Z (line 5 of the user's file) stays a G28 in the flattened program, at another
    line: the refusal (Z has a model) and the header's note (Z has none) name line 5."""
    from thermbench.precompensate.axes import run_precompensate_axes

    prog = tmp_path / "part.ngc"
    prog.write_text("G21 G90\n#<a> = 10\nG0 X#<a> Y0 Z5\nG1 X20 F600\nG28 Z0\nG0 X0\nM2\n")
    model, data = seed000_physics
    xz = tmp_path / "xz.yaml"
    xz.write_text(f"X: {{model: {model}, dataset: {data}}}\nZ: {{model: {model}, dataset: {data}}}\n")
    with pytest.raises(PrecompError) as exc:
        run_precompensate_axes(prog, xz, tmp_path / "out.ngc")
    assert re.search(rf"{re.escape(str(prog))}:5 \(line \d+ of the program as flattened by rs274\): G28 with a Z word", str(exc.value))
    x = tmp_path / "x.yaml"
    x.write_text(f"X: {{model: {model}, dataset: {data}}}\n")
    res = run_precompensate_axes(prog, x, tmp_path / "out.ngc")
    assert f"{prog}:5 (line" in res.as_written["Z"]
    header = [ln for ln in res.text.splitlines() if ln.startswith("(axis Z")][0]
    assert f"{prog}:5 [line" in header and header.count("(") == 1 and header.endswith(")")
    with pytest.raises(PrecompError, match=rf"{re.escape(str(prog))}:5 \(line \d+ of the program as flattened by rs274\)"):
        run_precompensate(prog, model, tmp_path / "out_z.ngc", dataset=data, axis="Z")  # one axis: the same


def test_rs274_killed_by_a_signal_is_run_again_then_named(tmp_path, monkeypatch):
    """Two rs274 at once can kill each other (SIGBUS, seen 1 run in 3 with six at once): they take
    turns, and a run killed by a signal is run again; killed every time, the error says so in one
    line instead of flattening a cut-short output."""
    import os

    import thermbench.linuxcnc.rs274 as r

    real = shutil.which("rs274")
    count = tmp_path / "count"
    fake = tmp_path / "rs274"
    # the first run dies of SIGBUS, the ones after run the real interpreter
    fake.write_text(f"#!/bin/sh\necho x >> {count}\n[ $(wc -l < {count}) -eq 1 ] && kill -BUS $$\nexec {real} \"$@\"\n")
    fake.chmod(0o755)
    monkeypatch.setattr(r, "rs274_path", lambda: str(fake))
    prog = tmp_path / "part.ngc"
    prog.write_text("G21 G90\nG0 X1 Y2\nG1 X5 F100\nM2\n")
    calls, _ = r.run_rs274(prog)
    assert [c[0] for c in calls].count("STRAIGHT_FEED") == 1 and count.read_text().count("x") == 2
    fake.write_text(f"#!/bin/sh\necho x >> {count}\nkill -BUS $$\n")
    os.remove(count)
    with pytest.raises(FlattenError, match=r"part.ngc: LinuxCNC's rs274 was killed by signal 7 in each of 3 runs") as exc:
        r.run_rs274(prog)
    assert count.read_text().count("x") == 3 and "\n" not in str(exc.value)
