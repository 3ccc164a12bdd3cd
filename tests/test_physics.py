"""The finite-difference model against analytic solutions, conservation, convergence
and the seed 000 paper numbers."""

import math
from dataclasses import replace

import numpy as np
import pytest

from thermbench.sim.effects import Effect
from thermbench.sim.model import Motion, ScrewThermalModel
from thermbench.sim.parts import CoreParams, Numerics, Screw

from .conftest import SEED000_MATERIAL, SEED000_SCREW, seed000_motion


class UniformSource(Effect):
    """Test-only effect: a uniform heat source over the whole screw."""

    id = "uniform_source_test"

    def __init__(self, power_W):
        self.power_W = power_W

    def sources(self, geom, drive):
        w = np.full(geom.n_nodes, 1.0 / geom.n_nodes)
        return [(w, np.full(drive.t_s.shape, self.power_W))]


def _still(duration_s):
    """Axis parked at 0 for the whole time (no nut heat when k4 = 0)."""
    return Motion(t_s=[0.0, duration_s], axis_mm=[0.0, 0.0], feed_mm_min=[0.0, 0.0])


@pytest.mark.parametrize("method", ["macro", "explicit"])
def test_steady_state_uniform_source_with_convection_matches_analytic(method):
    """lambda A T'' - h pi D T + q' = 0, insulated at x = 0, convective end face at
    x = L: T = T_inf + C cosh(m x) (textbook fin with uniform generation)."""
    # no bearing section and a vanishing nut: convection acts on the whole surface
    screw = Screw(length_m=0.8, diameter_m=0.034, nut_length_m=1e-9, fixed_bearing_length_m=0.0)
    h, lam, power = 26.0, 566.3, 10.0
    core = CoreParams(k1_W_m2K_per_mm_min=0.0, k2_W_m2K=h, k3_W_per_mm_min=0.0, k4_W_per_mm_min=0.0,
                      lambda_W_mK=lam, pf_m=-0.1)  # fmt: skip
    dx = 0.005  # explicit stability: lambda dt / (rho c dx^2) = 0.32 < 0.5
    model = ScrewThermalModel(screw, SEED000_MATERIAL, core, [UniformSource(power)],
                              Numerics(dx_m=dx, dt_s=0.05, macro_dt_s=20.0))  # fmt: skip
    duration = 6 * 3600.0
    hist = model.run(_still(duration), method=method)
    theta = hist.theta_C[-1]
    area = screw.area_m2
    per = math.pi * screw.diameter_m
    m = math.sqrt(h * per / (lam * area))
    L = screw.length_m
    t_inf = power / L / (h * per)
    c = -h * t_inf / (lam * m * math.sinh(m * L) + h * math.cosh(m * L))
    x = (np.arange(theta.size) + 0.5) * dx
    analytic = t_inf + c * np.cosh(m * x)
    # time constant rho c D / 4h ~ 1100 s: 6 h is ~19 of them
    assert np.max(np.abs(theta - analytic)) < 1e-3 * analytic.max()


@pytest.mark.parametrize("method", ["macro", "explicit"])
def test_conduction_only_decay_of_a_cosine_mode(method):
    """No convection, no sources, insulated ends: theta = cos(pi x / L) decays as
    exp(-(lambda / rho c)(pi / L)^2 t) and the mean temperature is conserved."""
    core = CoreParams(0.0, 0.0, 0.0, 0.0, 566.3, -0.1)
    screw = Screw(0.8, 0.034, 0.05, 0.0)
    dx = 0.005
    model = ScrewThermalModel(screw, SEED000_MATERIAL, core, [], Numerics(dx_m=dx, dt_s=0.05, macro_dt_s=5.0))
    x = (np.arange(int(round(0.8 / dx))) + 0.5) * dx
    theta0 = 2.0 + np.cos(np.pi * x / 0.8)
    t_end = 1800.0
    hist = model.run(_still(t_end), theta0_C=theta0, method=method)
    kappa = 566.3 / (SEED000_MATERIAL.density_kg_m3 * SEED000_MATERIAL.heat_capacity_J_kgK)
    rate = kappa * (np.pi / 0.8) ** 2
    for k in (len(hist.t_s) // 3, len(hist.t_s) - 1):
        t = hist.t_s[k]
        expected = 2.0 + np.exp(-rate * t) * np.cos(np.pi * x / 0.8)
        assert np.max(np.abs(hist.theta_C[k] - expected)) < 5e-3 * np.exp(-rate * t) + 1e-9
        assert abs(hist.theta_C[k].mean() - 2.0) < 1e-9


def test_energy_balance_on_the_seed000_loading():
    """Stored heat = input - convected within 0.5 %, and the input is what seed 000
    §4.1 says: (k3 + k4) v over the moving time."""
    tr, motion = seed000_motion(9000.0)
    model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL)
    hist = model.run(motion)
    g = hist.geom
    stored = g.cap_J_K * hist.theta_C[-1].sum()
    heat_in = hist.heat_in_J.sum()
    convected = hist.convected_J.sum()
    assert abs(stored - (heat_in - convected)) < 0.005 * heat_in
    # independent count of the input: QB + QN = (k3 + k4) v during motion
    c = model.core
    moving = motion.feed_mm_min > 0
    expected_in = np.sum((c.k3_W_per_mm_min + c.k4_W_per_mm_min) * motion.feed_mm_min[moving]) * 0.1
    assert abs(heat_in - expected_in) < 0.01 * expected_in


@pytest.mark.parametrize("feed", [3000.0, 9000.0])
def test_halving_dx_and_dt_changes_error_field_by_less_than_0p1_um(feed):
    grid = np.arange(0.0, 501.0, 50.0)
    fields = []
    for dx, dt in ((0.01, 0.1), (0.005, 0.05)):
        _, motion = seed000_motion(feed, dt_s=dt)
        model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, numerics=Numerics(dx_m=dx, dt_s=dt, macro_dt_s=10.0))
        fields.append(model.run(motion).error_field_um(grid))
    assert np.max(np.abs(fields[0] - fields[1])) < 0.1


def test_fast_integrator_matches_the_explicit_seed000_scheme():
    _, motion = seed000_motion(9000.0, warm_s=2400, cool_s=1200, warm2_s=600)
    model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL)
    grid = np.arange(0.0, 501.0, 25.0)
    fast = model.run(motion, method="macro").error_field_um(grid)
    ref = model.run(motion, method="explicit").error_field_um(grid)
    assert np.max(np.abs(fast - ref)) < 0.1
    assert ref.max() > 10.0  # a real signal, not two zeros


def test_extra_nut_heat_of_an_effect_matches_the_explicit_scheme():
    """The macro path averages an effect's extra nut heat over the nut's coverage in a
    second pass; the explicit scheme adds it sample by sample (an independent route)."""
    from thermbench.sim.registry import make_effect

    _, motion = seed000_motion(9000.0, warm_s=2400, cool_s=1200, warm2_s=600)
    model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(k4_W_per_mm_min=0.0),
                              effects=[make_effect("quadratic_friction_heat")])  # fmt: skip
    grid = np.arange(0.0, 501.0, 25.0)
    fast = model.run(motion, method="macro").error_field_um(grid)
    ref = model.run(motion, method="explicit").error_field_um(grid)
    assert ref.max() > 1.0  # the effect's heat alone moves the screw
    assert np.max(np.abs(fast - ref)) < 0.02 * ref.max()


def test_a_prepared_run_serves_models_that_differ_in_heat_gains_only():
    """Identification re-runs one motion with other k1..k4 and lambda: one prepare() serves
    them; a model with another Pf refuses it."""
    _, motion = seed000_motion(6000.0, warm_s=2400, cool_s=1200, warm2_s=600)
    amb = 20.0 + 0.3 * np.sin(motion.t_s / 2000.0)
    a = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams())
    b = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(k1_W_m2K_per_mm_min=0.002, k2_W_m2K=20.0,
                          k3_W_per_mm_min=0.0, k4_W_per_mm_min=0.002, lambda_W_mK=30.0))  # fmt: skip
    grid = np.arange(0.0, 501.0, 50.0)
    shared = a.prepare(motion, ambient_C=amb)
    np.testing.assert_allclose(b.run_prepared(shared).error_field_um(grid),
                               b.run(motion, ambient_C=amb).error_field_um(grid), atol=1e-12, rtol=0)  # fmt: skip
    assert not np.allclose(a.run_prepared(shared).error_field_um(grid), b.run_prepared(shared).error_field_um(grid))
    # the heat inputs made for a and b are kept with the run (by k3, k4 and the heating effects), read-only;
    # a model with a's gains and other conductances reuses a's and still gets its own field
    assert len(shared.heat) == 2 and all(not q[0].flags.writeable for q in shared.heat.values())
    c = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(k1_W_m2K_per_mm_min=0.003, lambda_W_mK=60.0))
    np.testing.assert_allclose(c.run_prepared(shared).error_field_um(grid),
                               c.run(motion, ambient_C=amb).error_field_um(grid), atol=1e-12, rtol=0)  # fmt: skip
    assert len(shared.heat) == 2
    other_pf = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(pf_m=0.1))
    with pytest.raises(ValueError, match="another screw, numerics or Pf"):
        other_pf.run_prepared(shared)


def test_kept_inputs_stay_within_their_byte_budget(monkeypatch):
    """What a run keeps is bounded by KEEP_BYTES: the bytes held are counted as values come
    and are replaced, past the budget what was kept is dropped, and a value larger than the
    budget alone is returned but not kept."""
    from thermbench.sim import prepared as sim_prepared

    monkeypatch.setattr(sim_prepared, "KEEP_BYTES", 1000)
    kept = sim_prepared.Kept()
    a = kept.keep("a", (np.zeros(50), 3.0))  # 400 bytes
    assert a[0].flags.writeable is False and kept.nbytes == 400
    kept.keep("b", (np.zeros(50), np.zeros(25)))  # 600 more: 1000, at the budget
    assert set(kept) == {"a", "b"} and kept.nbytes == 1000
    kept.keep("b", (np.zeros(10),))  # replaced: 400 + 80
    assert kept.nbytes == 480
    kept.keep("c", (np.zeros(66),))  # 528 more would pass 1000: the rest is dropped
    assert set(kept) == {"c"} and kept.nbytes == 528
    big = (np.zeros(126),)  # 1008 bytes alone
    assert kept.keep("d", big) is big and "d" not in kept and big[0].flags.writeable and kept.nbytes == 528
    kept.clear()
    assert kept.nbytes == 0 and not kept
    # a run's caches travel with it (a pickled or copied Prepared): the count stays the bytes held
    import copy
    import pickle

    kept.keep("a", (np.zeros(50),))
    for other in (pickle.loads(pickle.dumps(kept)), copy.deepcopy(kept)):
        assert set(other) == {"a"} and other.nbytes == 400
        other.keep("b", (np.zeros(25),))
        assert other.nbytes == 600


def test_runs_integrated_together_match_each_alone_and_superpose():
    """run_prepared_many integrates models that differ in heat gains in one pass (one
    factorisation per step, the runs' substitutions interleaved): each history equals the
    model run alone, and the field is linear in the gains (the heat equation with fixed
    conductances), so zero, bearing-only and nut-only runs add up to the full one."""
    from thermbench.sim.registry import make_effect
    from thermbench.sim.model import run_prepared_many

    _, motion = seed000_motion(6000.0, warm_s=2400, cool_s=1200, warm2_s=600)

    def model(k3, k4, k_motor):
        return ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(k3_W_per_mm_min=k3, k4_W_per_mm_min=k4),
                                 effects=[make_effect("motor_heat", k_motor_W_per_mm_min=k_motor)])  # fmt: skip

    models = [model(0, 0, 0), model(1e-3, 0, 0), model(0, 1e-3, 0), model(0, 0, 1e-3), model(1e-3, 1e-3, 1e-3),
              ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(k1_W_m2K_per_mm_min=0.002))]  # fmt: skip
    p = models[0].prepare(motion)
    together = run_prepared_many(p, models)
    for m, h in zip(models, together):
        alone = ScrewThermalModel(m.screw, m.material, m.core, m.effects, m.numerics).run(motion)
        np.testing.assert_array_equal(h.theta_C, alone.theta_C)
        np.testing.assert_array_equal(h.convected_J, alone.convected_J)
        for name in alone.housing_C:
            np.testing.assert_array_equal(h.housing_C[name], alone.housing_C[name])
    th = [h.theta_C for h in together]
    # no heat, no initial rise, constant ambient: the field stays exactly at zero
    assert not np.any(th[0]) and not np.any(together[0].convected_J)
    assert th[4].max() > 1.0
    np.testing.assert_allclose(th[4] - th[0], (th[1] - th[0]) + (th[2] - th[0]) + (th[3] - th[0]), atol=1e-9 * th[4].max())
    # other conductances (k1) are another integration, not a column of the first
    assert not np.allclose(th[5], th[4])


def test_error_at_readings_equals_the_error_field_at_the_steps():
    """error_um reads the elongation at the steps its readings fall between only; at the
    steps themselves it equals the full error field (each step's elongation summed alone)."""
    _, motion = seed000_motion(6000.0, warm_s=2400, cool_s=1200, warm2_s=600)
    model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(pf_m=-0.05))
    h = model.run(motion, ambient_C=20.0 + 0.4 * np.sin(motion.t_s / 1500.0))
    grid = np.array([0.0, 120.0, 333.0, 500.0])
    field = h.error_field_um(grid)
    ks = np.array([0, 7, 8, 40, h.t_s.size - 1])
    t = np.repeat(h.t_s[ks], grid.size)
    x = np.tile(grid, ks.size)
    np.testing.assert_allclose(h.error_um(t, x).reshape(ks.size, grid.size), field[ks], rtol=0, atol=1e-12)
    # between two steps: linear in time
    mid = 0.5 * (h.t_s[7] + h.t_s[8])
    np.testing.assert_allclose(h.error_um(np.full(grid.size, mid), grid), 0.5 * (field[7] + field[8]), atol=1e-12)


def test_paper_check_seed000_x_axis_table1_table3_table2():
    """seed 000 X axis (Table 1, Table 3) under Table 2 loading: max thermal error
    20-90 um, rising with feed (the paper measured up to 57 um)."""
    model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams())
    grid = np.arange(0.0, 501.0, 50.0)
    peaks = []
    for feed in (3000.0, 6000.0, 9000.0):
        _, motion = seed000_motion(feed)
        peaks.append(model.run(motion).error_field_um(grid).max())
    assert all(20.0 < p < 90.0 for p in peaks), peaks
    assert peaks[0] < peaks[1] < peaks[2]


def test_error_is_zero_at_the_fixed_end_and_grows_away_from_it():
    _, motion = seed000_motion(6000.0, warm_s=1800, cool_s=0, warm2_s=0)
    model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL)
    hist = model.run(motion)
    pf_mm = model.core.pf_m * 1000.0
    assert abs(hist.error_um([hist.t_s[-1]], [pf_mm])[0]) < 1e-12  # TEm(0) = 0 (seed 000 §3.2)
    e = hist.error_field_um(np.arange(0.0, 501.0, 50.0))[-1]
    assert np.all(np.diff(e) > 0)


def test_pf_positive_mirrors_the_axis():
    """Pf > 0: the axis runs towards the fixed end, the error changes sign (seed 000 §3.2)."""
    _, motion = seed000_motion(6000.0, warm_s=1800, cool_s=0, warm2_s=0)
    neg = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(pf_m=-0.141)).run(motion)
    mirrored = Motion(motion.t_s, -motion.axis_mm, motion.feed_mm_min)
    pos = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(pf_m=0.141)).run(mirrored)
    grid = np.arange(0.0, 501.0, 50.0)
    np.testing.assert_allclose(pos.error_field_um(-grid), -neg.error_field_um(grid), atol=1e-9)


def test_fields_of_one_run_read_together_equal_each_read_alone():
    """errors_um reads a run's fields in one pass (identification's basis): each row equals the
    field read alone, whatever its effects add (a constraint on the elongation, an offset); a
    read plan made for another Pf is refused."""
    from thermbench.sim.registry import make_effect
    from thermbench.sim.history import errors_um
    from thermbench.sim.model import run_prepared_many

    _, motion = seed000_motion(6000.0, warm_s=2400, cool_s=1200, warm2_s=600)
    amb = 20.0 + 0.3 * np.sin(motion.t_s / 2000.0)
    core = CoreParams(pf_m=-0.05)
    models = [
        ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, core, effects=[make_effect("ambient_drift")]),
        ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(pf_m=-0.05, k4_W_per_mm_min=0.003),
                          effects=[make_effect("ambient_drift"), make_effect("fixed_fixed_constraint", kappa=0.4)]),
        ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, core,
                          effects=[make_effect("ambient_drift"), make_effect("origin_drift", beta_um_per_K=2.0)]),
    ]  # fmt: skip
    hists = run_prepared_many(models[0].prepare(motion, ambient_C=amb), models)
    rng = np.random.default_rng(3)
    t = np.sort(rng.uniform(0.0, hists[0].t_s[-1], 50))
    x = rng.uniform(0.0, 500.0, 50)
    plan = hists[0].read_plan(t, x)
    together = errors_um(hists, plan)
    alone = np.stack([h.error_um(t, x) for h in hists])
    np.testing.assert_allclose(together, alone, rtol=0, atol=1e-12)
    assert np.ptp(together[1] - together[0]) > 1.0 and np.ptp(together[2] - together[0]) > 0.1  # the effects act
    other = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(pf_m=-0.1)).run(motion, ambient_C=amb)
    with pytest.raises(ValueError, match="another Pf"):
        errors_um([other], plan)
    # fields of another grid or another material are not read with this plan or these fields
    coarse = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, core, numerics=Numerics(dx_m=0.02)).run(motion, ambient_C=amb)
    with pytest.raises(ValueError, match="another grid"):
        errors_um([coarse], plan)
    steel = replace(SEED000_MATERIAL, alpha_per_K=2 * SEED000_MATERIAL.alpha_per_K)
    other_material = ScrewThermalModel(SEED000_SCREW, steel, core, effects=[make_effect("ambient_drift")])
    with pytest.raises(ValueError, match="screw, material or grid"):
        errors_um([hists[0], other_material.run_prepared(models[0].prepare(motion, ambient_C=amb))], plan)


@pytest.mark.parametrize("pf_m", [-0.05, 0.6])
def test_readings_sum_the_field_as_the_hand_formula_and_the_face_read_do(pf_m):
    """A field no effect adjusts is read by its node sums at the readings (kernels.read_node_sums):
    on a field uniform along the screw and linear in time, with the ambient drifting, the error is
    alpha (theta(t) - dTa(t)) x + alpha dTa(t) Px (seed 000 §3.2 and §2.2, x the nut's distance
    from Pf, the sign flipped for Pf > 0), computed by hand; on a simulated field it equals the
    read through the elongation at every face (taken when an effect adjusts it: here a
    constraint that holds nothing, kappa = 0), at readings and over every step."""
    from thermbench.sim.registry import make_effect
    from thermbench.sim.history import errors_um

    _, motion = seed000_motion(6000.0, warm_s=2400, cool_s=1200, warm2_s=600)
    amb = 20.0 + 0.3 * np.sin(motion.t_s / 2000.0)
    model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams(pf_m=pf_m), effects=[make_effect("ambient_drift")])
    h = model.run(motion, ambient_C=amb)
    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(0.0, h.t_s[-1], 40))
    px = rng.uniform(0.0, 500.0, 40)
    assert np.ptp(h.ambient_C) > 0.1
    # by hand: a field 0.5 K + 1e-4 K/s t everywhere on the screw
    uniform = replace(h, theta_C=np.repeat((0.5 + 1e-4 * h.t_s)[:, None], h.theta_C.shape[1], axis=1))
    dta = np.interp(t, h.t_s, h.ambient_C) - h.ta0_C
    sign = 1.0 if pf_m <= 0 else -1.0
    x_m = np.clip(sign * (px / 1000.0 - pf_m), 0.0, SEED000_SCREW.length_m)
    alpha = SEED000_MATERIAL.alpha_per_K
    by_hand = sign * (alpha * (0.5 + 1e-4 * t - dta) * x_m + alpha * dta * px / 1000.0) * 1e6
    plan = h.read_plan(t, px)
    np.testing.assert_allclose(errors_um([uniform], plan)[0], by_hand, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(errors_um([uniform], h.read_plan(t, px, rows=False))[0], by_hand, rtol=1e-9, atol=1e-9)
    # the simulated field, by its node sums and through the faces
    faces = replace(h, effects=[*h.effects, make_effect("fixed_fixed_constraint", kappa=0.0)])
    assert np.ptp(errors_um([h], plan)) > 1.0
    np.testing.assert_allclose(errors_um([h, faces], plan)[0], errors_um([h, faces], plan)[1], rtol=0, atol=1e-10)
    grid = np.arange(0.0, 501.0, 50.0)
    np.testing.assert_allclose(h.error_field_um(grid), faces.error_field_um(grid), rtol=0, atol=1e-10)


def test_a_lagged_signal_is_the_first_order_lag_and_is_kept_when_asked():
    """ThermalHistory.signal: the speed through a lag tau is y[k+1] = a y[k] + (1 - a) v[k],
    a = exp(-dt/tau) (computed here by the recursion, step by step), and a temperature rise
    through a lag starts at its first value; with a shared ``lagged`` dict the same array is
    returned again (read-only), equal to the one computed without it."""
    _, motion = seed000_motion(6000.0, warm_s=1200, cool_s=600, warm2_s=300)
    h = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, CoreParams()).run(motion)
    rise = np.linspace(0.0, 3.0, h.t_s.size)
    h = replace(h, signals={**h.signals, "T_nut": rise})
    dt, tau = float(h.t_s[1] - h.t_s[0]), 900.0
    a = math.exp(-dt / tau)
    v = np.asarray(h.signals["speed"]) / 1000.0
    y = np.zeros(h.t_s.size)
    for k in range(v.size):
        y[k + 1] = a * y[k] + (1 - a) * v[k]
    np.testing.assert_allclose(h.signal("speed", tau), y, rtol=1e-12, atol=1e-15)
    z = np.empty(rise.size)
    z[0] = rise[0]
    for k in range(1, rise.size):
        z[k] = a * z[k - 1] + (1 - a) * rise[k]
    np.testing.assert_allclose(h.signal("T_nut", tau), z, rtol=1e-12, atol=1e-15)
    kept = replace(h, lagged={})
    first = kept.signal("speed", tau)
    assert kept.signal("speed", tau) is first and not first.flags.writeable
    np.testing.assert_array_equal(first, h.signal("speed", tau))
    assert not np.array_equal(kept.signal("speed", 60.0), first)
    with pytest.raises(KeyError, match="not available"):
        kept.signal("T_motor", tau)
