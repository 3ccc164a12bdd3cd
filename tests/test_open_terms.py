"""The open-ended terms (thermbench.sim.open_terms): each reproduces the canonical effect it
generalises where their forms meet (a second implementation of the same physics), follows
its signal as the hand computation says, and describes itself in words and numbers."""

import math

import numpy as np
import pytest

from thermbench.sim.open_terms import OPEN_TERMS
from thermbench.sim.registry import make_effect
from thermbench.sim.model import ScrewThermalModel
from thermbench.sim.parts import Numerics

from .conftest import SEED000_MATERIAL, SEED000_SCREW, seed000_motion

GRID = np.arange(0.0, 501.0, 50.0)


@pytest.fixture(scope="module")
def loading():
    _, motion = seed000_motion(6000.0, warm_s=3600, cool_s=2400, warm2_s=0)
    return motion


def _field(motion, effects=(), signals=None):
    model = ScrewThermalModel(SEED000_SCREW, SEED000_MATERIAL, effects=list(effects), numerics=Numerics())
    hist = model.run(motion, ambient_C=20.0, signals=signals)
    return hist, hist.error_field_um(GRID)


def test_the_open_terms_are_registered_apart_from_the_canonical_effects():
    assert set(OPEN_TERMS) == {"heat_source", "nut_heat_power", "driven_offset", "referenced_expansion"}


def test_a_heat_source_at_the_free_end_is_the_free_end_bearing(loading):
    """at_frac = 1, p = 1, no lag, q = kF x 6000 mm/min over the same 30 mm: the same heat in the
    same nodes as free_end_bearing_heat (dx 10 mm: three nodes of 1/3 each)."""
    kf = 0.8e-3
    _, ref = _field(loading, [make_effect("free_end_bearing_heat", kF_W_per_mm_min=kf, length_m=0.03)])
    src = make_effect("heat_source", q_W=kf * 6000.0, at_frac=1.0, p=1.0, tau_s=0.0, length_m=0.03)
    _, got = _field(loading, [src])
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9)
    assert np.abs(ref).max() > 1.0  # a real effect, um
    assert src.canonical() == "free_end_bearing_heat"


def test_a_heat_source_moves_continuously_along_the_screw(loading):
    """Its weights follow the centre by overlap, so the error changes smoothly with at_frac
    (what SLSQP needs), and the source heats where it is: far from the fixed end it moves the
    near targets less."""
    fields = [_field(loading, [make_effect("heat_source", q_W=5.0, at_frac=a)])[1][-1] for a in (0.5, 0.501, 0.502)]
    d1, d2 = fields[1] - fields[0], fields[2] - fields[1]
    assert np.abs(d1).max() < 0.05 and np.allclose(d1, d2, atol=0.01)
    _, base = _field(loading)
    _, near = _field(loading, [make_effect("heat_source", q_W=5.0, at_frac=0.1)])
    _, far = _field(loading, [make_effect("heat_source", q_W=5.0, at_frac=0.9)])
    assert (near - base)[-1, 1] > 1.1 * (far - base)[-1, 1] > 0


def test_nut_heat_with_exponent_two_is_the_viscous_friction(loading):
    k5 = 5e-8
    _, ref = _field(loading, [make_effect("quadratic_friction_heat", k5_W_per_mm_min2=k5)])
    term = make_effect("nut_heat_power", q_W=k5 * 6000.0**2, p=2.0)
    _, got = _field(loading, [term])
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9)
    assert term.canonical() == "quadratic_friction_heat"
    assert make_effect("nut_heat_power", p=1.2).canonical() is None


def test_an_offset_follows_its_signal_by_hand(loading):
    """g x lag_tau(speed): the speed's step means through y[k+1] = a y[k] + (1 - a) v[k], computed
    here by a plain loop; on a temperature channel, g x its rise."""
    g, tau = 2.0, 1800.0
    hist, base = _field(loading)
    hist2, got = _field(loading, [make_effect("driven_offset", g_um_per_unit=g, tau_s=tau, signal="speed")])
    v = hist.signals["speed"] / 1000.0  # m/min, step means
    a = math.exp(-(hist.t_s[1] - hist.t_s[0]) / tau)
    y = [0.0]
    for vk in v:
        y.append(a * y[-1] + (1 - a) * vk)
    np.testing.assert_allclose(got - base, g * np.array(y)[:, None] * np.ones(GRID.size), atol=1e-9)
    # a measured channel: 20 C + a ramp of 0.5 K/h; the offset is g x the rise, no lag
    t = np.array([0.0, 20000.0])
    _, got_t = _field(loading, [make_effect("driven_offset", g_um_per_unit=g, tau_s=0.0, signal="T_bed")],
                      signals={"T_bed": (t, 20.0 + 0.5 * t / 3600.0)})  # fmt: skip
    np.testing.assert_allclose((got_t - base)[:, 3], g * 0.5 * hist.t_s / 3600.0, atol=1e-9)


def test_an_expansion_is_zero_at_its_reference_point(loading):
    """a s(t) (Px - P0)/1000 with P0 = 1000 b/a: nothing at P0, a slope of a s/1000 per mm."""
    a_um, p0_mm = 6.0, 200.0
    term = make_effect("referenced_expansion", a_um_per_m_unit=a_um, b_um_per_unit=a_um * p0_mm / 1000.0, signal="T_bed")
    t = np.array([0.0, 20000.0])
    sig = {"T_bed": (t, 20.0 + t / 3600.0)}
    hist, base = _field(loading, signals=sig)
    _, got = _field(loading, [term], signals=sig)
    rise = (hist.t_s / 3600.0)[:, None]
    np.testing.assert_allclose(got - base, a_um * rise * (GRID[None, :] - p0_mm) / 1000.0, atol=1e-9)
    assert term.p0_mm == pytest.approx(p0_mm)


def test_the_terms_describe_themselves_in_words_and_numbers():
    ctx = {"length_m": 0.8, "sensors": {"T_bed": "bed", "T_amb": "ambient", "T_fb": "fixed_bearing_housing"},
           "travel_mm": (0.0, 500.0)}  # fmt: skip
    words = make_effect("heat_source", q_W=2.1, at_frac=0.775, p=1.0, tau_s=0.0).describe(ctx)
    assert "0.62 m along the screw" in words and "v^1.0" in words and "no lag" in words and "2.1 W at 6000 mm/min" in words
    words = make_effect("driven_offset", g_um_per_unit=6.5, tau_s=3.8 * 3600, signal="speed").describe(ctx)
    assert "6.5 µm per m/min of the axis speed" in words and "3.8 h" in words
    words = make_effect("referenced_expansion", a_um_per_m_unit=4.0, b_um_per_unit=0.8, signal="T_bed").describe(ctx)
    assert "about P0 = 200 mm" in words and "T_bed (bed)" in words
    # canonical special cases
    assert make_effect("heat_source", at_frac=0.05, tau_s=1800.0).canonical(ctx) == "motor_heat"
    assert make_effect("heat_source", at_frac=0.5).canonical(ctx) is None
    assert make_effect("driven_offset", signal="T_fb").canonical(ctx) == "origin_drift"
    assert make_effect("driven_offset", signal="T_bed").canonical(ctx) is None
    amb = make_effect("referenced_expansion", a_um_per_m_unit=11.7, b_um_per_unit=0.0, signal="T_amb")
    assert amb.canonical(ctx) == "ambient_drift"


def test_a_signal_the_model_lacks_is_named(loading):
    with pytest.raises(KeyError, match="T_bed"):
        _field(loading, [make_effect("driven_offset", signal="T_bed")])
