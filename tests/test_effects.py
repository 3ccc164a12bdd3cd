"""Every effect moves the error the way its physics says, and is exactly zero when off."""

import numpy as np
import pytest

from thermbench.sim.effects import EFFECTS, first_order_lag
from thermbench.sim.registry import effects_from_config, make_effect
from thermbench.sim.model import Motion, ScrewThermalModel

from .conftest import SEED000_MATERIAL, SEED000_SCREW, seed000_motion

GRID = np.arange(0.0, 501.0, 50.0)


@pytest.fixture(scope="module")
def loading():
    # 60 min warm at 6000 mm/min, 40 min cool, 600 N axial load while moving
    tr, motion = seed000_motion(6000.0, warm_s=3600, cool_s=2400, warm2_s=0, load_N=600.0)
    return motion


def _field(motion, effects=(), ambient=20.0):
    model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, effects=list(effects))
    hist = model.run(motion, ambient_C=ambient)
    return hist, hist.error_field_um(GRID)


def test_canonical_ids():
    assert set(EFFECTS) == {
        "ambient_drift", "free_end_bearing_heat", "motor_heat", "origin_drift",
        "fixed_fixed_constraint", "quadratic_friction_heat", "load_dependent_heat",
    }  # fmt: skip


@pytest.mark.parametrize("effect_id", sorted(EFFECTS))
def test_disabled_effect_is_exactly_zero(loading, effect_id):
    _, base = _field(loading)
    off = effects_from_config({effect_id: {"enabled": False}})
    assert off == []
    _, again = _field(loading, off)
    np.testing.assert_array_equal(base, again)


ZERO_STRENGTH = {
    "ambient_drift": {"amplitude_C": 0.0, "rate_C_per_h": 0.0},
    "free_end_bearing_heat": {"kF_W_per_mm_min": 0.0},
    "motor_heat": {"k_motor_W_per_mm_min": 0.0},
    "origin_drift": {"beta_um_per_K": 0.0},
    "fixed_fixed_constraint": {"kappa": 0.0},
    "quadratic_friction_heat": {"k5_W_per_mm_min2": 0.0},
    "load_dependent_heat": {"k6_W_per_N_mm_min": 0.0},
}


@pytest.mark.parametrize("effect_id", sorted(EFFECTS))
def test_zero_strength_effect_changes_nothing(loading, effect_id):
    _, base = _field(loading)
    _, zero = _field(loading, [make_effect(effect_id, **ZERO_STRENGTH[effect_id])])
    np.testing.assert_allclose(zero, base, atol=1e-12, rtol=0)


@pytest.mark.parametrize("effect_id", ["free_end_bearing_heat", "motor_heat", "quadratic_friction_heat", "load_dependent_heat"])
def test_extra_heat_makes_the_screw_grow_more(loading, effect_id):
    _, base = _field(loading)
    _, more = _field(loading, [make_effect(effect_id)])
    diff = more - base
    assert np.all(diff >= -1e-9)
    assert diff[:, -1].max() > 0.5  # a real change at the far end of the travel, um


def test_free_end_heat_acts_where_the_fixed_end_heat_does_not(loading):
    """Heat at the far end lengthens the part of the screw beyond the nut's
    stroke; heat at the fixed end all of it: per um at the far end, the free-end
    bearing moves the near targets less than the motor does."""
    _, base = _field(loading)
    _, free = _field(loading, [make_effect("free_end_bearing_heat", kF_W_per_mm_min=1e-3)])
    _, motor = _field(loading, [make_effect("motor_heat", k_motor_W_per_mm_min=1e-3)])
    k = -1
    near_free = (free - base)[k, 1] / (free - base)[k, -1]
    near_motor = (motor - base)[k, 1] / (motor - base)[k, -1]
    assert near_free < near_motor


def test_motor_heat_keeps_flowing_after_the_axis_stops():
    """A 10-min burst then rest: the screw's share from the lagging motor keeps
    rising after the stop, while the nut/bearing-heated base is already cooling."""
    tr, motion = seed000_motion(6000.0, warm_s=600, cool_s=3600, warm2_s=0)
    hist, base = _field(motion)
    _, motor = _field(motion, [make_effect("motor_heat", tau_s=1800.0)])
    diff = (motor - base)[:, -1]
    stop = np.searchsorted(hist.t_s, 600.0 + 60.0)  # after the burst and its measuring cycle
    later = np.searchsorted(hist.t_s, hist.t_s[stop] + 900.0)
    assert diff[later] > diff[stop] > 0
    assert base[later, -1] < base[stop, -1]
    # and the lag itself is a first-order response
    lag = first_order_lag(np.ones(100), 10.0, 100.0)
    np.testing.assert_allclose(lag[10], 1 - np.exp(-1.0), rtol=1e-12)


def test_quadratic_friction_grows_with_speed_squared():
    _, m3 = seed000_motion(3000.0, warm_s=1800, cool_s=0, warm2_s=0)
    _, m9 = seed000_motion(9000.0, warm_s=1800, cool_s=0, warm2_s=0)
    eff = [make_effect("quadratic_friction_heat", k5_W_per_mm_min2=1e-8)]
    d3 = _field(m3, eff)[1][-1, -1] - _field(m3)[1][-1, -1]
    d9 = _field(m9, eff)[1][-1, -1] - _field(m9)[1][-1, -1]
    assert d9 / d3 > 5.0  # v^2 gives 9x the heat (less convection lost at low speed)


def test_load_dependent_heat_needs_the_load_column():
    motion = Motion(t_s=[0.0, 600.0], axis_mm=[0.0, 500.0], feed_mm_min=[3000.0, 3000.0])
    model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, effects=[make_effect("load_dependent_heat")])
    with pytest.raises(ValueError, match="load_N"):
        model.run(motion)


def test_ambient_drift_follows_the_ambient_and_scales_with_position():
    t = np.arange(0.0, 6 * 3600.0, 1.0)
    still = Motion(t_s=t, axis_mm=np.zeros_like(t), feed_mm_min=np.zeros_like(t))
    ambient = 20.0 + np.minimum(t / 3600.0, 1.0)  # +1 K over the first hour, then steady
    base = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL).run(still, ambient_C=ambient, ambient_t_s=t)
    assert np.all(base.error_field_um(GRID) == 0.0)  # without the effect the ambient is taken as constant
    drift = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, effects=[make_effect("ambient_drift")])
    hist = drift.run(still, ambient_C=ambient, ambient_t_s=t)
    field = hist.error_field_um(GRID)
    alpha_um = SEED000_MATERIAL.alpha_per_K * 1e3  # um per K per mm
    k1 = np.searchsorted(hist.t_s, 3600.0)
    # while the ambient rises the screw lags behind it: TEm < 0, so the error stays
    # below the soaked value alpha dTa Px (seed 000 §2.2) but grows with position
    e1 = field[k1]
    assert np.all(np.diff(e1) > 0)
    assert np.all(e1[1:] < alpha_um * 1.0 * GRID[1:]) and e1[-1] > 0
    # soaked (5 h later, ~15 screw time constants): exactly alpha dTa Px
    np.testing.assert_allclose(field[-1], alpha_um * 1.0 * GRID, atol=0.01)


def test_origin_drift_is_position_independent(loading):
    hist, base = _field(loading)
    _, od = _field(loading, [make_effect("origin_drift", beta_um_per_K=3.0)])
    diff = od - base
    np.testing.assert_allclose(diff, diff[:, :1] * np.ones_like(diff), atol=1e-9)
    th = hist.housing_C["fixed_bearing_housing"]
    np.testing.assert_allclose(diff[:, 0], 3.0 * (th - th[0]), atol=1e-9)
    assert diff[:, 0].max() > 0.5


def test_fixed_fixed_constraint_suppresses_growth_and_bends_the_curve():
    # the nut works the middle of the travel: with both ends held the error curve
    # is a hump (seed 004: a parabola), not the fixed-free straight-ish line
    _, motion = seed000_motion(6000.0, warm_s=3600, cool_s=0, warm2_s=0)
    mid = Motion(motion.t_s, 150.0 + 0.4 * motion.axis_mm, motion.feed_mm_min)
    _, free = _field(mid)
    _, ff = _field(mid, [make_effect("fixed_fixed_constraint", kappa=1.0)])
    assert ff[-1, -1] < free[-1, -1]
    prof = ff[-1]
    k = int(np.argmax(prof))
    assert 0 < k < len(prof) - 1  # interior maximum
    coef = np.polyfit(GRID, prof, 2)
    assert coef[0] < 0  # concave, parabola-like
    model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, effects=[make_effect("fixed_fixed_constraint", kappa=1.0)])
    u = model.run(mid).elongation_um()
    np.testing.assert_allclose(u[:, -1], 0.0, atol=1e-9)  # kappa = 1: the far end does not move


def test_unknown_effect_or_parameter_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown effect 'spindle_heat'"):
        make_effect("spindle_heat")
    with pytest.raises(ValueError, match="no parameter"):
        make_effect("motor_heat", k_W=1.0)
