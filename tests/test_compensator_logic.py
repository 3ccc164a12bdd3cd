"""The compensator's cycle rules without a network (thermbench.compensator.control) and
its nodes file: input guard, regridding onto the model's sample period, stale and
backwards timestamps, restart after a long outage, rate limit, the error line."""

from __future__ import annotations

import math

import numpy as np
import pytest

from thermbench.compensator.control import CycleLogic, Flags, Reading
from thermbench.compensator.errorline import fit_line
from thermbench.compensator.settings import Settings
from thermbench.compensator.nodes import NodesError, load_nodes


class FakeModel:
    """The LiveModel interface; predicts ``a + b x + c x^2`` (+ ``shift`` from the last
    temperature), records every step and start."""

    temperatures = ["T_nut"]
    needs_load = False

    def __init__(self, period_s=1.0, a=5.0, b=0.02, c=0.0):
        self.period_s, self.a, self.b, self.c = period_s, a, b, c
        self.steps, self.starts, self.ready_s = [], 0, math.nan

    def start(self):
        self.starts += 1
        self.ready_s = math.nan
        self.steps = []

    def step(self, t_s, axis_mm, feed_mm_min, temps_C, load_N=0.0, measuring=False, operating=()):
        self.steps.append((t_s, axis_mm, feed_mm_min, list(temps_C), measuring))
        self.ready_s = t_s
        return 0

    def _total(self, t, x):
        """The error the model state at ``t`` (the last step at or before it) predicts."""
        past = [s for s in self.steps if s[0] <= t + 1e-12]
        return self.a + self.b * x + self.c * x * x + (past[-1][3][0] - 20.0 if past else 0.0)

    def predict(self, t_s, axis_mm):
        return 0, 0.0, float(self._total(t_s, axis_mm)), -1

    def predict_many(self, t_s, axis_mm):
        x = np.asarray(axis_mm, dtype=float)
        return np.zeros(x.size, dtype=int), self._total(t_s, x)


def _r(ts, x=100.0, feed=3000.0, temp=20.0, **extra):
    d = {"axis_mm": Reading(x, ts), "feed_mm_min": Reading(feed, ts), "T_nut_C": Reading(temp, ts)}
    d.update(extra)
    return d


def _logic(model=None, output="value", **kw):
    cfg = {"rate_limit_um_s": 1000.0, "ranges": {"temperature_C": [-20, 80]}, **kw}
    return CycleLogic(model or FakeModel(), Settings.from_config(cfg), output)


def test_compensation_is_minus_the_predicted_error_and_ramps_from_zero():
    lg = _logic()
    c = lg.cycle(_r(1000.0, x=100.0), now_wall_s=0.0)
    assert c.t_s == 0.0 and c.predicted_um == pytest.approx(5.0 + 0.02 * 100.0)
    assert c.value_um == 0.0 and c.flags == Flags.RATE_LIMITED  # no machine time has passed: no step yet
    c = lg.cycle(_r(1001.0, x=100.0), now_wall_s=0.1)
    assert c.value_um == pytest.approx(-7.0) and c.flags == 0
    err = _logic(convention="error")
    err.cycle(_r(0.0, x=100.0), 0.0)
    assert err.cycle(_r(1.0, x=100.0), 0.1).value_um == pytest.approx(7.0)


def test_rate_limit_holds_each_step_to_rate_times_machine_time():
    m = FakeModel(period_s=1.0, a=50.0, b=0.0)
    lg = _logic(m, rate_limit_um_s=10.0)
    vals, flags = [], []
    for k in range(8):
        c = lg.cycle(_r(1000.0 + k), now_wall_s=0.01 * k)
        vals.append(c.value_um)
        flags.append(c.flags)
    d = np.diff([0.0, *vals])
    assert np.all(np.abs(d) <= 10.0 * 1.0 + 1e-9)  # 10 µm/s over 1 s steps of machine time
    assert vals[0] == 0.0 and vals[5] == pytest.approx(-50.0)  # 0, -10, ..., -50 reached at the 6th cycle
    assert flags[1] & Flags.RATE_LIMITED and not flags[6] & Flags.RATE_LIMITED


def test_nan_and_out_of_range_temperatures_are_held_and_flagged():
    m = FakeModel()
    lg = _logic(m)
    lg.cycle(_r(0.0, temp=21.0), 0.0)
    c = lg.cycle(_r(1.0, temp=float("nan")), 0.1)
    assert c.flags & Flags.INPUT_HELD and c.held == ["T_nut_C"] and m.steps[-1][3] == [21.0]
    c = lg.cycle(_r(2.0, temp=500.0), 0.2)  # beyond ranges.temperature_C
    assert c.held == ["T_nut_C"] and m.steps[-1][3] == [21.0]
    c = lg.cycle({**_r(3.0), "T_nut_C": Reading(22.0, 3.0, good=False)}, 0.3)  # bad status from the server
    assert c.held == ["T_nut_C"]
    c = lg.cycle(_r(4.0, temp=23.0), 0.4)
    assert not c.held and c.flags & Flags.INPUT_HELD == 0 and m.steps[-1][3] == [23.0]


def test_a_temperature_older_than_the_axis_is_stale_and_held():
    m = FakeModel()
    lg = _logic(m, input_max_age_s=5.0)
    lg.cycle(_r(0.0, temp=21.0), 0.0)
    r = _r(30.0, temp=25.0)
    r["T_nut_C"] = Reading(25.0, 20.0)  # 10 s behind the axis
    c = lg.cycle(r, 0.1)
    assert c.held == ["T_nut_C"] and m.steps[-1][3] == [21.0]


def test_no_good_value_yet_means_no_sample_and_nothing_written():
    m = FakeModel()
    lg = _logic(m)
    c = lg.cycle(_r(0.0, temp=float("nan")), 0.0)
    assert c.flags & Flags.NOT_READY and c.flags & Flags.HELD and c.value_um is None and not m.steps


def test_model_is_stepped_on_its_grid_with_the_latest_values():
    m = FakeModel(period_s=1.0)
    lg = _logic(m)
    for i in range(31):  # 0.1 s cycles, positions moving
        lg.cycle(_r(500.0 + 0.1 * i, x=float(i)), 0.1 * i)
    assert [s[0] for s in m.steps] == [0.0, 1.0, 2.0, 3.0]
    assert [s[1] for s in m.steps] == [0.0, 10.0, 20.0, 30.0]  # the value read when the grid point passed


def test_stale_timestamps_hold_the_compensation():
    lg = _logic(stale_after_s=0.5)
    good = lg.cycle(_r(0.0), 0.0)
    assert not good.flags & Flags.HELD
    c = lg.cycle(_r(0.0), 0.3)
    assert not c.flags & Flags.STALE
    c = lg.cycle(_r(0.0, x=400.0), 0.9)  # same timestamp for 0.9 s of the client's clock
    assert c.flags & Flags.STALE and c.flags & Flags.HELD and c.value_um == good.value_um
    c = lg.cycle(_r(1.0), 1.0)
    assert not c.flags & (Flags.STALE | Flags.HELD)


def test_a_timestamp_going_backwards_is_refused():
    m = FakeModel()
    lg = _logic(m)
    lg.cycle(_r(10.0), 0.0)
    lg.cycle(_r(11.0), 0.1)
    n = len(m.steps)
    c = lg.cycle(_r(9.0, x=300.0), 0.2)
    assert c.flags & Flags.CLOCK and c.flags & Flags.HELD and len(m.steps) == n


def test_max_age_against_the_wall_clock():
    lg = _logic(max_age_s=1.0)
    c = lg.cycle(_r(100.0), now_wall_s=0.0, now_epoch_s=105.0)
    assert c.flags & Flags.STALE


def test_an_outage_longer_than_the_runtime_bridges_restarts_the_model():
    m = FakeModel()
    lg = _logic(m)
    lg.cycle(_r(0.0), 0.0)
    lg.cycle(_r(1.0), 0.1)
    c = lg.cycle(_r(200.0), 0.2)  # 199 s without samples (> TB_MAX_GAP_S 60 s)
    assert c.flags & Flags.RESTARTED and m.starts == 1 and m.steps == [(200.0, 100.0, 3000.0, [20.0], False)]


def test_error_line_of_a_linear_error_is_exact_and_ref_is_where_offset_applies():
    m = FakeModel(a=3.0, b=0.04)
    lg = _logic(m, output="line", line={"travel_mm": [0.0, 500.0], "n_points": 11, "ref_mm": 100.0}, rate_limit_um_s=1e9)
    lg.cycle(_r(0.0), 0.0)
    c = lg.cycle(_r(1.0), 0.1)
    # comp = -(3 + 0.04 x): at ref 100 mm -7 µm, slope -0.04 µm/mm = -40 µm/m
    assert c.line.ref_mm == 100.0
    assert c.line.offset_um == pytest.approx(-7.0) and c.line.slope_um_per_m == pytest.approx(-40.0)
    assert c.value_um is None


def test_error_line_is_the_least_squares_line_of_a_curved_error():
    x = np.linspace(0.0, 500.0, 21)
    comp = -(2.0 + 0.01 * x + 4e-5 * x * x)
    ln = fit_line(x, comp, ref_mm=0.0)
    resid = comp - ln.at(x)
    assert abs(resid.sum()) < 1e-9 and abs((resid * x).sum()) < 1e-6  # normal equations of least squares


def test_settings_name_the_bad_key():
    with pytest.raises(ValueError, match="rate_limit_um_s"):
        Settings.from_config({"rate_limit_um_s": 0})
    with pytest.raises(ValueError, match="line.travel_mm"):
        Settings.from_config({"line": {"travel_mm": [500, 0]}})
    with pytest.raises(ValueError, match="convention"):
        Settings.from_config({"convention": "minus"})
    with pytest.raises(ValueError, match="line.travel_mm"):
        CycleLogic(FakeModel(), Settings.from_config({}), "line")


NODES = """
inputs:
  axis_mm: "ns=2;s=X.Position_mm"
  feed_mm_min: "ns=2;s=X.Feed_mm_min"
  temperatures: {T_nut: "ns=2;s=X.T_nut_C"}
outputs:
  value: {node: "ns=2;s=X.TempComp_um", unit: um}
"""


@pytest.mark.parametrize(
    "text, message",
    [
        (NODES.replace("T_nut:", "T_bed:"), "inputs.temperatures: the model reads sensor"),
        (NODES.replace("unit: um", "unit: inch"), "outputs.value.unit"),
        (NODES + "  colour: red\n", "outputs.colour"),
        (NODES.replace("ns=2;s=X.TempComp_um", "ns=2;s=X.Feed_mm_min"), "both an input and an output"),
        ("inputs: [", "not valid YAML"),
    ],
)
def test_nodes_file_errors_name_the_key(tmp_path, text, message):
    p = tmp_path / "nodes.yaml"
    p.write_text(text)
    with pytest.raises(NodesError, match=message) as e:
        load_nodes(p, ["T_nut"])
    assert str(p) in str(e.value)


def test_nodes_file_needs_the_nodes_of_the_output_form(tmp_path):
    p = tmp_path / "nodes.yaml"
    p.write_text(NODES)
    assert load_nodes(p, ["T_nut"]).output_ids() == {"value": "ns=2;s=X.TempComp_um"}
    with pytest.raises(NodesError, match="outputs.line"):
        load_nodes(p, ["T_nut"], output="line")
    with pytest.raises(NodesError, match="inputs.load_N"):
        load_nodes(p, ["T_nut"], needs_load=True)


def test_no_step_after_an_outage_or_a_freeze():
    """After 30 s without fresh values (held), a 30 K jump still ramps at the limit: dt per
    cycle is at most one sample period."""
    m = FakeModel(period_s=1.0, a=0.0, b=0.0)
    lg = _logic(m, rate_limit_um_s=1.0)
    lg.cycle(_r(0.0), 0.0)
    lg.cycle(_r(1.0), 0.1)
    v0 = lg.value_um
    lg.hold(Flags.DISCONNECTED)  # the outage
    c = lg.cycle(_r(31.0, temp=50.0), 0.2)  # 30 s later, the error is 30 µm larger
    assert abs(c.value_um - v0) <= 1.0 + 1e-9 and c.flags & Flags.RATE_LIMITED
    frozen = _logic(FakeModel(a=0.0, b=0.0), rate_limit_um_s=1.0)
    frozen.cycle(_r(0.0), 0.0)
    frozen.cycle(_r(1.0), 0.1)
    c = frozen.cycle(_r(101.0, temp=50.0), 0.2)  # a 100 s jump of machine time (freeze, then a sample)
    assert abs(c.value_um) <= 1.0 + 1e-9


def test_the_limit_acts_on_change_in_time_not_along_the_axis():
    """Moving 100 mm in one cycle changes the value by the error's gradient at once; a change
    in time (30 K) at the same position ramps."""
    m = FakeModel(period_s=1.0, a=0.0, b=0.1)  # 0.1 µm/mm along the axis
    lg = _logic(m, rate_limit_um_s=1.0)
    lg.cycle(_r(0.0, x=0.0), 0.0)
    lg.cycle(_r(1.0, x=0.0), 0.1)
    c = lg.cycle(_r(1.05, x=100.0), 0.15)  # same model state, axis moved 100 mm
    assert c.value_um == pytest.approx(-10.0) and not c.flags & Flags.RATE_LIMITED
    c = lg.cycle(_r(2.0, x=100.0, temp=50.0), 0.2)  # +30 µm in time at this position
    assert c.value_um == pytest.approx(-10.0 - 0.95) and c.flags & Flags.RATE_LIMITED  # 1 µm/s x 0.95 s


def test_start_up_ramps_from_the_controllers_value_and_undo_forgets_an_unwritten_cycle():
    lg = _logic(FakeModel(a=0.0, b=0.0), rate_limit_um_s=1.0)
    lg.resume(value_um=-30.0)
    c = lg.cycle(_r(0.0), 0.0)
    assert c.value_um == -30.0  # not a step to 0
    c = lg.cycle(_r(1.0), 0.1)
    assert c.value_um == pytest.approx(-29.0)
    lg.cycle(_r(2.0), 0.2)
    lg.undo()  # that write failed
    assert lg.value_um == pytest.approx(-29.0) and lg.hold(Flags.DISCONNECTED).value_um == pytest.approx(-29.0)


def test_client_clock_for_servers_that_stamp_on_change_and_a_heartbeat_for_staleness():
    m = FakeModel()
    lg = _logic(m, clock="client", stale_after_s=0.5)
    for i in range(4):  # timestamps never advance (values unchanged), the client's clock does
        c = lg.cycle({**_r(7.0), "heartbeat": Reading(i, 7.0)}, now_wall_s=float(i), now_epoch_s=1000.0 + i)
        assert not c.flags & Flags.STALE
    assert [s[0] for s in m.steps] == [0.0, 1.0, 2.0, 3.0]
    lg.cycle({**_r(7.0), "heartbeat": Reading(3, 7.0)}, now_wall_s=3.3, now_epoch_s=1003.3)
    c = lg.cycle({**_r(7.0), "heartbeat": Reading(3, 7.0)}, now_wall_s=4.0, now_epoch_s=1004.0)
    assert c.flags & Flags.STALE  # the heartbeat stopped for 1 s > stale_after_s


def test_a_clock_that_stays_behind_starts_a_new_timeline():
    m = FakeModel()
    lg = _logic(m, stale_after_s=0.5)
    lg.cycle(_r(100.0), 0.0)
    assert lg.cycle(_r(10.0), 0.1).flags & Flags.CLOCK
    c = lg.cycle(_r(11.0), 0.7)  # still behind after stale_after_s: the server's clock restarted
    assert c.flags & Flags.RESTARTED and m.starts == 1 and c.t_s == 0.0


@pytest.mark.parametrize("cfg, key", [({"line": {"travel_mm": [0]}}, "line.travel_mm"),
                                      ({"ranges": {"temperature_C": [1]}}, "ranges.temperature_C"),
                                      ({"stale_after_s": -1}, "stale_after_s"), ({"clock": "gps"}, "clock"),
                                      ({"rate_limit_um_s": "fast"}, "rate_limit_um_s")])  # fmt: skip
def test_bad_numbers_name_their_key(cfg, key):
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        Settings.from_config(cfg)


def test_namespace_uris_are_resolved_against_the_servers_namespace_array():
    """OPC UA Part 6 5.3.1.10: nsu=<uri>;<id> names the namespace by URI; the server's
    NamespaceArray gives its index (here 3). Other forms pass unchanged; an unknown URI or a
    malformed id is a one-line CompensatorError naming the node and the server's namespaces."""
    from thermbench.compensator.errors import CompensatorError
    from thermbench.compensator.opcua import resolve_node_id

    array = ["http://opcfoundation.org/UA/", "urn:server", "urn:vendor:plc", "urn:thermbench:sim-cnc", "urn:a;b"]
    assert resolve_node_id("nsu=urn:thermbench:sim-cnc;s=X.Position_mm", array, "input axis_mm") == "ns=3;s=X.Position_mm"
    assert resolve_node_id("nsu=urn:vendor:plc;i=6001", array, "x") == "ns=2;i=6001"
    assert resolve_node_id("nsu=urn:a%3Bb;s=Y", array, "x") == "ns=4;s=Y"  # ';' escaped in the URI
    assert resolve_node_id("ns=2;s=X.Position_mm", array, "x") == "ns=2;s=X.Position_mm"
    with pytest.raises(CompensatorError, match=r"^nodes file: input T_nut_C node 'nsu=urn:other;s=T': the server has no namespace "
                                               r"'urn:other'; its namespaces: \['http://opcfoundation.org/UA/'"):
        resolve_node_id("nsu=urn:other;s=T", array, "input T_nut_C")
    with pytest.raises(CompensatorError, match="expected nsu=<namespace URI>;<identifier>"):
        resolve_node_id("nsu=urn:thermbench:sim-cnc", array, "output value")


def test_the_status_line_says_cycles_times_machine_time_compensation_and_flags():
    from types import SimpleNamespace

    from thermbench.compensator.cyclelog import status_line

    c = SimpleNamespace(t_s=3600.4, value_um=-12.345, flags=int(Flags.STALE) | int(Flags.HELD))
    line = status_line(41, c, [1.0, 2.0, 6.0])
    assert line == ("cycle 42: 3.00 ms mean, 6.00 ms max over 3 cycles; machine time 3600 s; compensation -12.35 um; "
                    "STALE|HELD")  # the flags in the order of the flags word's bits
    assert status_line(0, SimpleNamespace(t_s=math.nan, value_um=None, flags=0), [0.5]).endswith(
        "machine time -; compensation -; OK")


def test_probe_readings_correct_the_compensation_as_the_python_filter_does_once_per_timestamp():
    """A probe input (measured error, source timestamp) updates the C runtime's filter in the cycle
    logic: every cycle's written value is minus the total corrected as thermbench.bench.adapt's filter
    corrects it (a second implementation), a probe is taken once per new timestamp, and a warm
    restart goes on with the correction."""
    from thermbench.bench.adapt import ProbeFilter, ProbeParams

    noise = {"q_bias_um2_per_h": 40.0, "q_gain_per_h": 1e-2, "r_um2": 0.05, "bias0_um": 3.0, "gain0": 0.1}
    lg = _logic(probe=noise)
    ref = ProbeFilter(ProbeParams(**noise), 0.0)
    probe_at = {30: 9.5, 60: 11.0, 61: 11.0, 90: 7.0}  # t -> measured; the reading at 61 repeats 60's stamp
    stamp = None
    for k in range(120):
        temp = 20.0 + 0.05 * k
        extra = {}
        if k in probe_at:
            stamp = 1000.0 + (60 if k == 61 else k)
        if stamp is not None:
            extra["probe"] = Reading(probe_at[int(stamp - 1000.0)], stamp)
        c = lg.cycle(_r(1000.0 + k, x=50.0, temp=temp, **extra), now_wall_s=0.01 * k)
        total = 5.0 + 0.02 * 50.0 + (temp - 20.0)
        if k in (30, 60, 90):  # a new stamp: taken (61 repeats 60's: not)
            assert c.flags & Flags.PROBE and c.probe_um == probe_at[k]
            ref.probe(float(k), total, probe_at[k])
        else:
            assert not c.flags & Flags.PROBE
        want, _ = ref.correct(float(k), total)
        assert c.predicted_um == pytest.approx(total) and c.correction_um == pytest.approx(want - total, abs=1e-9)
        if k > 0:
            assert c.value_um == pytest.approx(-want, abs=1e-9)
    assert ref.n_probes == 3
    # warm restart: the saved state (with the model's samples) gives the same correction afterwards
    st = lg.state()
    again = _logic(probe=noise)
    again.warm_start(st, [(k, 50.0, 3000.0, 0.0, 0.0, 20.0 + 0.05 * k) for k in range(120)])
    assert again.filter.state() == lg.filter.state()
    assert again._corrected(150.0, 3.0) == pytest.approx(ref.correct(150.0, 3.0)[0])


@pytest.mark.parametrize("policy", ["report", "hold", "limit"])
def test_outside_the_training_envelope_is_flagged_and_held_when_asked(policy):
    """The model's manifest says its nut rose at most 2 K: a rise past it flags EXTRAPOLATING on
    every cycle it lasts; 'hold' keeps the last value written inside, 'report' writes as usual,
    'limit' writes the interval's inner edge (the prediction moved toward 0 by the half-width
    q (1 + kappa d), d the distance in widths of the range)."""
    m = FakeModel()
    m.manifest = {"envelope": {"sensors": ["T_nut"], "operating": [], "names": ["rise:T_nut", "rate:T_nut"],
                               "lo": [0.0, -100.0], "hi": [2.0, 100.0], "width": [2.0, 200.0], "rate_tau_s": 600.0},
                  "interval": {"level": 0.9, "kappa": 0.5, "q_um": 1.5}}  # fmt: skip
    lg = _logic(m, extrapolation=policy)
    out = [lg.cycle(_r(1000.0 + k, temp=20.0 + 0.1 * k), now_wall_s=0.01 * k) for k in range(40)]
    ext = [bool(c.flags & Flags.EXTRAPOLATING) for c in out]
    assert ext == [k > 20 for k in range(40)]  # the rise passes 2 K after sample 20 (0.1 K per sample)
    inside = out[20].value_um
    if policy == "hold":
        assert all(c.value_um == inside and c.flags & Flags.HELD for c in out[21:])
    elif policy == "report":
        assert all(not c.flags & Flags.HELD for c in out[21:]) and out[-1].value_um < inside - 1.0
    else:
        for k, c in enumerate(out):
            d = max(0.0, (0.1 * k - 2.0) / 2.0)  # the rise beyond 2 K, in widths of 2 K
            want = c.predicted_um if k <= 20 else max(c.predicted_um - 1.5 * (1 + 0.5 * d), 0.0)  # positive here
            assert c.predicted_um > 0 and (k == 0 or c.value_um == pytest.approx(-want, abs=1e-9)), k
        assert out[-1].value_um > -out[-1].predicted_um + 1.5
    with pytest.raises(Exception, match="config key 'extrapolation': expected report, hold or limit, got 'clip'"):
        _logic(m, extrapolation="clip")
    m.manifest.pop("interval")
    with pytest.raises(Exception, match="config key 'extrapolation': limit needs the model's interval"):
        _logic(m, extrapolation="limit")


def test_a_history_hole_is_a_time_without_any_input():
    """history_hole (warm restart across an outage, from the server's history): a data-change
    historian stores a value when it changes, so one input without a point for minutes held its
    value; only a time in which no input has a point is a hole. By hand: an outage from 1000 to 1130 s."""
    from thermbench.compensator.client import history_hole

    axis = np.arange(1001.0, 1130.0, 5.0)  # moving: a point every 5 s
    feed = np.array([1003.0])  # one change, then 127 s at the same feed
    measuring = np.array([], dtype=float)  # no change in the whole outage
    assert history_hole(1000.0, 1130.0, [axis, feed, measuring], 60.0) == ""
    # the axis stands still from 1041 s to the end: 89 s with no point of any input
    why = history_hole(1000.0, 1130.0, [axis[axis <= 1041.0], feed, measuring], 60.0)
    assert why == ("the server's history has no value of any input for 89 s (from 41 s after the saved state), more "
                   "than the 60 s the runtime bridges")  # fmt: skip
    assert history_hole(1000.0, 1130.0, [np.array([]), np.array([])], 60.0).startswith(
        "the server's history has no value of any input for 130 s (from 0 s after")
    # points outside the outage (a server's bound values) do not fill it; a gap of exactly max_gap_s is bridged
    assert history_hole(1000.0, 1130.0, [np.array([900.0, 1200.0])], 200.0) == ""
    assert "for 130 s" in history_hole(1000.0, 1130.0, [np.array([900.0, 1200.0])], 60.0)
    assert history_hole(1000.0, 1120.0, [np.array([1060.0])], 60.0) == ""


def _faults_manifest(max_um=1000.0):
    """Limits of two sensors that heat together (T_b = 2 T_a above their first readings, a line the
    others rule reads), as an export writes them (thermbench/bench/faults.py)."""
    return {"faults": {"limits": {"sensors": ["T_a", "T_b"], "rise_lo_K": [0.0, 0.0], "rise_hi_K": [5.0, 10.0],
                                  "rate_max_K_h": [10.0, 20.0], "flat_s": [10.0, 10.0], "icpt": [0.0, 0.0],
                                  "coef": [[0.0, 0.5], [2.0, 0.0]], "tol_K": [2.0, 2.0], "tau_s": 600.0},
                       "bounds": {"max_um": max_um, "rate_um_s": 1.0}}}  # fmt: skip


class TwoSensorModel(FakeModel):
    temperatures = ["T_a", "T_b"]

    def _total(self, t, x):  # 1 µm per K of T_b's rise
        past = [s for s in self.steps if s[0] <= t + 1e-12]
        return 0.0 * np.asarray(x, dtype=float) + (past[-1][3][1] - 20.0 if past else 0.0)


def _r2(ts, a, b):
    return {"axis_mm": Reading(100.0, ts), "feed_mm_min": Reading(3000.0, ts), "T_a_C": Reading(a, ts),
            "T_b_C": Reading(b, ts)}  # fmt: skip


def test_an_open_sensor_is_flagged_from_its_sample_and_the_model_reads_it_as_the_other_predicts():
    """T_b opens (850 °C) at cycle 10: SENSOR_FAULT on that cycle and every one after, the cycle
    names it, and the model is stepped with 20 + 2 x T_a's rise in its place (the line of the
    manifest), so the compensation keeps following T_a; the written value never jumps."""
    m = TwoSensorModel()
    m.manifest = _faults_manifest()
    lg = CycleLogic(m, Settings.from_config({"rate_limit_um_s": 1000.0, "ranges": {"temperature_C": [-300, 900]}}))
    out = []
    for k in range(20):
        a = 20.0 + 0.1 * k
        out.append(lg.cycle(_r2(1000.0 + k, a, 850.0 if k >= 10 else 20.0 + 0.2 * k), now_wall_s=0.01 * k))
    assert [bool(c.flags & Flags.SENSOR_FAULT) for c in out] == [k >= 10 for k in range(20)]
    assert all(c.faulty == ["T_b"] for c in out[10:]) and all(c.faulty == [] for c in out[:10])
    for k, step in enumerate(m.steps):
        assert step[3][1] == pytest.approx(20.0 + 0.2 * k)  # read as logged before, reconstructed after: 2 x 0.1 k
    assert max(abs(b.value_um - a.value_um) for a, b in zip(out, out[1:])) < 0.25


def test_the_compensation_is_held_to_the_manifest_bound():
    m = TwoSensorModel()
    m.manifest = _faults_manifest(max_um=1.0)
    lg = CycleLogic(m, Settings.from_config({"rate_limit_um_s": 1000.0, "ranges": {"temperature_C": [-20, 80]}}))
    out = [lg.cycle(_r2(1000.0 + k, 20.0 + 0.1 * k, 20.0 + 0.2 * k), now_wall_s=0.01 * k) for k in range(12)]
    for k, c in enumerate(out):
        raw = 0.2 * k  # T_b's rise, 1 µm per K
        assert c.value_um == pytest.approx(-min(raw, 1.0))  # compensation = -error, bounded at 1 µm
        assert bool(c.flags & Flags.BOUNDED) == (raw > 1.0 + 1e-9)


def test_a_user_s_bound_overrides_the_manifest_s_and_a_bad_one_names_its_key():
    """bound_um: 0.5 over the manifest's 1.0: the compensation stops at 0.5 µm (BOUNDED beyond)."""
    m = TwoSensorModel()
    m.manifest = _faults_manifest(max_um=1.0)
    lg = CycleLogic(m, Settings.from_config({"rate_limit_um_s": 1000.0, "bound_um": 0.5,
                                             "ranges": {"temperature_C": [-20, 80]}}))  # fmt: skip
    out = [lg.cycle(_r2(1000.0 + k, 20.0 + 0.1 * k, 20.0 + 0.2 * k), now_wall_s=0.01 * k) for k in range(12)]
    for k, c in enumerate(out):
        raw = 0.2 * k
        assert c.value_um == pytest.approx(-min(raw, 0.5))
        assert bool(c.flags & Flags.BOUNDED) == (raw > 0.5 + 1e-9)
    with pytest.raises(Exception, match="bound_um"):
        Settings.from_config({"bound_um": -1.0})
