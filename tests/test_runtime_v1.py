"""The physics kind's payload v2 (effects as sections ``(code, n_params, params...)``, each read
by its own C file, embedded/src/tb_fx_*.c) and the v1 files written before it.

``tests/data/physics_v1_*.tbm`` were written by thermbench at commit 02b87b3 (``_encode_physics``,
payload v1: 41 fixed values) from a ``PhysicsModel(effects=<all seven canonical effects>,
identify=[], dx_m=0.02, dt_s=0.5, macro_dt_s=10.0)`` fitted on seed001_vmc_x (state1, state2,
with a synthetic load_N column) with every heat gain then set to its ``reference`` value, once
without an ambient sensor (``ambient_drift`` simulates it) and once with the ``auto`` ambient
sensor. ``*.expected.txt`` is what ``tb_replay`` built from embedded/ at that commit printed for
:func:`synthetic_stream`. The runtime must reproduce those lines exactly (``%.17g``), from the
v1 files and from v2 files carrying the same numbers.
"""

from __future__ import annotations

import math
import re
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest

from thermbench.export import ExportError, Kind, ModelFileError, fileformat, pack, runtime, unpack
from thermbench.export.encoding import PHYSICS_CORE, SENSOR_VALS, PhysicsGrid, effect_sections
from thermbench.sim.effects import (
    EFFECTS,
    AmbientDrift,
    FixedFixedConstraint,
    FreeEndBearingHeat,
    LoadDependentHeat,
    MotorHeat,
    OriginDrift,
    QuadraticFrictionHeat,
)
from thermbench.sim.parts import Housing

DATA = Path(__file__).parent / "data"
FIXTURES = ["physics_v1_ambient_drift", "physics_v1_ambient_sensor"]
# payload v1 after the core: the slots of every effect (thermbench at 02b87b3, PHYSICS_PARAMS[19:])
V1_SLOTS = ("ambient_mode amb_amplitude_C amb_period_s amb_phase_s amb_rate_C_per_h free_end kF free_k_nodes motor "
            "k_motor tau_motor_s k5 load k6 fixed_fixed kappa origin_drift beta_um_per_K housing_tau_s "
            "housing_gain_K_per_W housing_gain_K_per_mm_min housing_coupling").split()  # fmt: skip


def synthetic_stream(hours: float = 2.5, every_q_s: float = 60.0) -> str:
    """A tb_replay stream: 1-s samples of a reciprocating axis with varying feed and load and one
    drifting temperature (the ambient), queries every ``every_q_s`` at three positions."""
    t = np.arange(0.0, hours * 3600.0, 1.0)
    feed = np.where((t // 1200) % 3 == 2, 0.0, 4000.0 + 2000.0 * np.sin(t / 700.0))
    axis = 250.0 + 230.0 * np.sin(t / 15.0)
    load = 600.0 + 300.0 * np.sin(t / 500.0)
    amb = 20.0 + 0.8 * np.sin(t / 2500.0) + t / 36000.0
    lines = [f"Q {float(tq)!r} {x!r}" for tq in t[:: int(every_q_s)] for x in (0.0, 250.0, 480.0)]
    lines += [f"S {a:.17g} {b:.17g} {c:.17g} {d:.17g} 0 {e:.17g}" for a, b, c, d, e in zip(t, axis, feed, load, amb)]
    return "\n".join(lines) + "\n"


def _body_at(payload, S: int) -> int:
    """Index of the physics body: after the period, the sensor block and the geometric block."""
    at = 1 + S * (1 + SENSOR_VALS)
    gtype, n = int(payload[at]), int(payload[at + 1])
    at += 4 + (2 * n if gtype == 2 else (n if gtype == 1 else 0))
    return at + 2 + int(payload[at])


def physics_v1_payload(payload, dims, housing=(900.0, 0.45, 0.0, 0.5)) -> list[float]:
    """The v1 payload of a v2 one (the v1 encoder, as a test helper): the same blocks and core,
    then the 22 fixed slots; ``housing`` fills the housing slots when origin_drift is absent."""
    p = [float(v) for v in payload]
    at = _body_at(p, dims[0])
    head, core = p[:at], p[at : at + len(PHYSICS_CORE)]
    at += len(PHYSICS_CORE)
    sec = {}
    for _ in range(int(p[at])):
        code, k = int(p[at + 1]), int(p[at + 2])
        sec[code] = p[at + 3 : at + 3 + k]
        at += 2 + k
    assert at + 1 == len(p), "the sections end the payload"
    mode = 1.0 if dims[0] else (2.0 if 1 in sec else 0.0)
    on = lambda c: float(c in sec)  # noqa: E731
    slots = [mode, *sec.get(1, [0.0] * 4), on(5), *sec.get(5, [0.0, 0.0]), on(4), *sec.get(4, [0.0, 0.0]),
             *sec.get(2, [0.0]), on(3), *sec.get(3, [0.0]), on(6), *sec.get(6, [0.0]), on(7),
             *sec.get(7, [0.0, *housing])]  # fmt: skip
    assert len(slots) == len(V1_SLOTS)
    return head + core + slots


def v2_from_v1(mf: fileformat.ModelFile) -> list[float]:
    """A v2 payload carrying the numbers of a v1 file, the effects' sections written by the
    effect classes themselves (``export_code``, ``export_params``)."""
    p = [float(v) for v in mf.payload]
    at = _body_at(p, mf.dims[0])
    core = dict(zip(PHYSICS_CORE, p[at : at + len(PHYSICS_CORE)]))
    v1 = dict(zip(V1_SLOTS, p[at + len(PHYSICS_CORE) :]))
    house = Housing(v1["housing_tau_s"], v1["housing_gain_K_per_W"], v1["housing_gain_K_per_mm_min"],
                    v1["housing_coupling"], source="fixed_bearing", screw_at="fixed_end")  # fmt: skip
    grid = PhysicsGrid(int(core["n_nodes"]), int(core["n_bearing"]), core["dx_m"], core["dt_s"], core["macro_dt_s"],
                       {"fixed_bearing_housing": house})  # fmt: skip
    effects = [  # every flag of both fixtures is set: the model has all seven
        OriginDrift(v1["beta_um_per_K"]), MotorHeat(v1["k_motor"], v1["tau_motor_s"]),
        AmbientDrift(v1["amb_amplitude_C"], v1["amb_period_s"], v1["amb_phase_s"], v1["amb_rate_C_per_h"]),
        FreeEndBearingHeat(v1["kF"], v1["free_k_nodes"] * core["dx_m"]), QuadraticFrictionHeat(v1["k5"]),
        LoadDependentHeat(v1["k6"]), FixedFixedConstraint(v1["kappa"]),
    ]  # fmt: skip
    assert all(v1[f] == 1.0 for f in ("free_end", "motor", "load", "fixed_fixed", "origin_drift"))
    return p[:at] + [core[k] for k in PHYSICS_CORE] + effect_sections(effects, grid, "fixture")


def replay(path: Path, stream: str, sanitize: bool = False) -> str:
    res = subprocess.run([str(runtime.build("tb_replay", sanitize=sanitize)), str(path)], input=stream,
                         capture_output=True, text=True)  # fmt: skip
    assert res.returncode == 0, res.stderr
    return res.stdout


def info_error(path: Path) -> int | None:
    """The runtime's error code opening ``path`` (ASan/UBSan build), None when it opens."""
    res = subprocess.run([str(runtime.build("tb_replay", sanitize=True)), "--info", str(path)], capture_output=True,
                         text=True)  # fmt: skip
    assert "Sanitizer" not in res.stderr, res.stderr
    if res.returncode == 0:
        return None
    m = re.search(r"error (-\d+):", res.stderr)
    assert res.returncode == 3 and m, res.stderr
    return int(m.group(1))


@pytest.fixture(scope="module")
def stream() -> str:
    return synthetic_stream()


# ------------------------------------------------------------- v1 files ---
@pytest.mark.parametrize("name", FIXTURES)
def test_v1_files_written_before_the_plugins_give_the_same_numbers(name, stream):
    """The v1 reader maps the fixed slots to the effects' C files: every answer is the one the
    runtime gave before the split, to the last bit (also under ASan/UBSan)."""
    f = DATA / f"{name}.tbm"
    mf = fileformat.read(f)
    assert mf.kind == Kind.PHYSICS and mf.version == 1 and struct.unpack_from("<H", f.read_bytes(), 4) == (1,)
    expected = (DATA / f"{name}.expected.txt").read_text()
    assert len(expected.splitlines()) == 450 and "nan" not in expected
    assert replay(f, stream) == expected
    assert replay(f, stream, sanitize=True) == expected


@pytest.mark.parametrize("name", FIXTURES)
def test_a_v2_file_with_the_same_numbers_gives_the_same_results(name, stream, tmp_path):
    """The same model as v2 (the sections written by the effect classes): the same answers as
    the v1 file gave before the split; converted back to v1 by the test's v1 encoder, the payload
    is the original file's, value for value."""
    mf = fileformat.read(DATA / f"{name}.tbm")
    v2 = v2_from_v1(mf)
    assert len(v2) == mf.payload.size - len(V1_SLOTS) + 1 + 7 * 2 + 4 + 2 + 2 + 1 + 1 + 1 + 5
    f = tmp_path / "v2.tbm"
    fileformat.write(f, Kind.PHYSICS, mf.dims, v2)
    assert fileformat.read(f).version == 2
    assert replay(f, stream) == (DATA / f"{name}.expected.txt").read_text()
    back = np.asarray(physics_v1_payload(v2, mf.dims), dtype="<f4")
    assert back.view("<u4").tolist() == mf.payload.view("<u4").tolist()


def test_the_python_reader_knows_each_kinds_versions():
    mlr = pack(Kind.MLR_CURVE, [2, 1], [0.0, 1.5, -2.25])
    assert struct.unpack_from("<H", mlr, 4) == (1,) and unpack(mlr).version == 1
    phys = (DATA / "physics_v1_ambient_drift.tbm").read_bytes()
    mf = unpack(phys)
    assert unpack(pack(Kind.PHYSICS, mf.dims, mf.payload)).version == 2  # written as the latest
    assert pack(Kind.PHYSICS, mf.dims, mf.payload, version=1) == phys  # the v1 bytes, rewritten
    with pytest.raises(ModelFileError, match="MLR_CURVE: payload version 2; this thermbench writes 1 to 1"):
        pack(Kind.MLR_CURVE, [2, 1], [0.0], version=2)
    bad = mlr[:4] + struct.pack("<H", 2) + mlr[6:-4]
    with pytest.raises(ModelFileError, match="m.tbm: format version 2 of kind MLR_CURVE, which has versions 1 to 1"):
        unpack(bad + struct.pack("<I", zlib.crc32(bad)), "m.tbm")
    bad = phys[:4] + struct.pack("<H", 3) + phys[6:-4]
    with pytest.raises(ModelFileError, match="format version 3, this thermbench reads 1 to 2"):
        unpack(bad + struct.pack("<I", zlib.crc32(bad)), "m.tbm")


# --------------------------------------------------------- bad v2 files ---
def _v2(tmp_path, mutate=None, version=None, dims=None, name="bad.tbm") -> Path:
    mf = fileformat.read(DATA / "physics_v1_ambient_drift.tbm")
    p = v2_from_v1(mf)
    if mutate:
        p = mutate(p, _body_at(p, mf.dims[0]) + len(PHYSICS_CORE))
    f = tmp_path / name
    f.write_bytes(pack(Kind.PHYSICS, dims or mf.dims, p, version))
    return f


def _section(p, e, code):
    """Index of the section of effect ``code`` in payload ``p`` whose effect list starts at ``e``."""
    at = e + 1
    for _ in range(int(p[e])):
        if int(p[at]) == code:
            return at
        at += 2 + int(p[at + 1])
    raise KeyError(code)


def _set(p, i, v):
    return p[:i] + [v] + p[i + 1 :]


@pytest.mark.parametrize(
    "mutate, code",
    [
        (None, None),  # the unchanged file opens
        (lambda p, e: _set(p, _section(p, e, 7), 9.0), -8),  # an effect code the runtime does not know
        (lambda p, e: _set(p, _section(p, e, 7), 6.0), -8),  # a code twice (and out of order)
        (lambda p, e: _set(p, _section(p, e, 4) + 1, 3.0), -6),  # n_params not the effect's
        (lambda p, e: _set(p, _section(p, e, 4) + 3, 0.0), -8),  # motor_heat tau_s 0
        (lambda p, e: _set(p, _section(p, e, 5) + 3, 51.0), -8),  # free-end slices beyond the 50 of the screw
        (lambda p, e: _set(p, _section(p, e, 5) + 3, 2.5), -8),  # ... not whole
        (lambda p, e: _set(p, _section(p, e, 1) + 3, 0.0), -8),  # a simulated ambient of period 0
        (lambda p, e: _set(p, _section(p, e, 7) + 3, -900.0), -8),  # the housing's tau_s < 0
        (lambda p, e: _set(p, e, 9.0), -8),  # more effects than TBI_MAX_EFFECTS (8)
        (lambda p, e: p[:-1], -6),  # the last section cut short
        (lambda p, e: p + [0.0], -6),  # a value after the last section
        (lambda p, e: p[:e] + [0.0], None),  # no effects: the core alone opens
    ],
)
def test_the_runtime_refuses_a_bad_effect_section_with_its_code(tmp_path, mutate, code):
    assert info_error(_v2(tmp_path, mutate)) == code


def test_versions_the_runtime_does_not_have_are_refused(tmp_path):
    assert info_error(_v2(tmp_path, version=1)) in (-6, -8)  # a v2 payload read as v1: wrong layout
    good = _v2(tmp_path).read_bytes()
    three = good[:4] + struct.pack("<H", 3) + good[6:-4]
    f = tmp_path / "v3.tbm"
    f.write_bytes(three + struct.pack("<I", zlib.crc32(three)))
    assert info_error(f) == -3


def test_an_ambient_section_beside_a_measured_ambient_is_not_used(tmp_path, stream):
    """With an ambient sensor, thermbench convects to the measured ambient (AmbientDrift.ambient_C);
    the runtime does too, whatever the section says (its period is then not checked)."""
    mf = fileformat.read(DATA / "physics_v1_ambient_sensor.tbm")
    p = v2_from_v1(mf)
    e = _body_at(p, 1) + len(PHYSICS_CORE)
    a = _section(p, e, 1)
    f0, f1 = tmp_path / "a.tbm", tmp_path / "b.tbm"
    fileformat.write(f0, Kind.PHYSICS, mf.dims, p)
    fileformat.write(f1, Kind.PHYSICS, mf.dims, p[:a + 2] + [5.0, 0.0, 0.0, 9.0] + p[a + 6 :])
    assert info_error(f1) is None
    expected = (DATA / "physics_v1_ambient_sensor.expected.txt").read_text()
    assert replay(f0, stream) == replay(f1, stream) == expected


# ------------------------------------------------------------ python ---
GRID = PhysicsGrid(50, 2, 0.02, 0.5, 10.0, {"fixed_bearing_housing": Housing(900.0, 0.45, 0.0, 0.5, "fixed_bearing",
                                                                             "fixed_end")})  # fmt: skip


def test_effects_without_a_c_implementation_are_refused_in_one_line():
    from thermbench.sim.open_terms import HeatSource

    with pytest.raises(ExportError) as exc:
        effect_sections([MotorHeat(), HeatSource()], GRID, "m")
    msg = str(exc.value)
    assert msg.startswith("m: effect 'heat_source' has no C implementation; the runtime implements [")
    assert "'motor_heat'" in msg and "\n" not in msg

    class TunedMotor(MotorHeat):  # changes the physics: not motor_heat's C file by inheritance
        id = "tuned_motor"

        def sources(self, geom, drive):
            return []

    with pytest.raises(ExportError, match=r"^m: effect 'tuned_motor' has no C implementation;"):
        effect_sections([TunedMotor()], GRID, "m")


def test_an_effect_says_why_its_values_cannot_be_exported():
    odd = {"fixed_bearing_housing": Housing(900.0, 0.45, 0.0, 0.5, source="nut", screw_at="nut")}
    grid = PhysicsGrid(50, 2, 0.02, 0.5, 10.0, odd)
    with pytest.raises(ExportError, match=r"^m: effect 'origin_drift': the runtime models the fixed-bearing housing"):
        effect_sections([OriginDrift()], grid, "m")
    with pytest.raises(ExportError, match=r"^m: effect 'free_end_bearing_heat': length_m = 1.5 m covers 75 slices"):
        effect_sections([FreeEndBearingHeat(length_m=1.5)], GRID, "m")
    assert effect_sections([OriginDrift(2.5)], GRID, "m") == [1.0, 7.0, 5.0, 2.5, 900.0, 0.45, 0.0, 0.5]
    # sections in code order whatever the model's order; k of the free end as sources() heats it
    assert effect_sections([FreeEndBearingHeat(1e-3, 0.05), QuadraticFrictionHeat(3e-8)], GRID, "m") == [
        2.0, 2.0, 1.0, 3e-8, 5.0, 2.0, 1e-3, float(math.ceil(0.05 / 0.02 - 1e-9))]  # fmt: skip


def test_every_canonical_effect_has_its_c_file_with_the_same_code():
    """tb_registry.def lists TB_EFFECT(code, name) for each effect the Python classes export, with
    the class's export_code, and tb_fx_<name>.c declares that code."""
    src = runtime.embedded_dir() / "src"
    listed = {name: int(code) for code, name in re.findall(r"^TB_EFFECT\((\d+), (\w+)\)", (src / "tb_registry.def").read_text(), re.M)}
    assert listed == {i: cls.export_code for i, cls in EFFECTS.items()}
    for name, code in listed.items():
        c = (src / f"tb_fx_{name}.c").read_text()
        assert re.search(rf"tbi_effect_{name} = \{{\s*\.code = {code}, \.n_params = (\d+)", c), name
        n = int(re.search(r"\.n_params = (\d+)", c).group(1))
        cls = EFFECTS[name]
        assert len(cls().export_params(GRID)) == n, name
