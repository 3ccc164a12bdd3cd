"""Flattening part programs with LinuxCNC's interpreter (thermbench/linuxcnc/rs274.py) and
pre-compensating the result. LinuxCNC's ``rs274`` must be installed (``make test`` installs
``linuxcnc-uspace``): missing, these tests fail."""

from __future__ import annotations

import math
import re
import shutil

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
    with pytest.raises(FlattenError, match=r"bad.ngc: LinuxCNC's rs274 refused it: ") as e:
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
