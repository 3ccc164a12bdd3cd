"""Warm restarts of the compensator (thermbench/compensator/state.py, CycleLogic.warm_start):
the state saved by one process, re-stepped by the next. The reference is an uninterrupted run
of the same model over the same readings; the contrast is a cold start on the warm machine
(the failure guarded against: the warm machine taken as the zero)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from thermbench.compensator.control import CycleLogic, Flags, Reading
from thermbench.compensator.settings import Settings
from thermbench.compensator.state import StateStore
from thermbench.export.native import LiveModel

T0 = 1.7e9  # machine time is a server's epoch timestamp


def readings(t: float) -> dict[str, Reading]:
    """A warming axis: the nut heats towards +4 K (150 s), the bed drifts; the axis reciprocates."""
    ts = T0 + t
    return {"axis_mm": Reading(350.0 + 200.0 * math.sin(t / 20.0), ts), "feed_mm_min": Reading(6000.0, ts),
            "T_nut_C": Reading(20.0 + 4.0 * (1.0 - math.exp(-t / 150.0)), ts), "T_bed_C": Reading(20.0 + 0.3 * t / 400, ts)}  # fmt: skip


def logic(model_dir) -> CycleLogic:
    lg = CycleLogic(LiveModel(model_dir), Settings(rate_limit_um_s=1000.0))
    lg.keep_stepped = True  # as the compensator does when it has a state store
    return lg


def run(lg: CycleLogic, times) -> list:
    return [lg.cycle(readings(t), now_wall_s=t) for t in times]


def test_a_warm_restart_goes_on_as_if_nothing_happened(seed001_exports, tmp_path):
    model = seed001_exports / "mlr"
    # the reference: one process that saw the same 30 s outage (no readings) without restarting
    whole = run(logic(model), [*range(200), *range(230, 400)])
    first = logic(model)
    run(first, range(200))
    store = StateStore(tmp_path / "state.json")
    store.sync(first.stepped, first.starts)
    store.save(first.state())
    store.close()
    saved = json.loads((tmp_path / "state.json").read_text())
    assert saved["rows"] == 200 and saved["last_ts"] == T0 + 199 and saved["k_last"] == 199

    header, rows = StateStore(tmp_path / "state.json").load()
    second = logic(model)  # a new process: a fresh runtime
    warm, why = second.resume_decision(header, rows, T0 + 230, {k: r.value for k, r in readings(230).items()})
    assert warm and why == "gap 31.0 s, 200 samples re-stepped"
    second.warm_start(header, rows)
    after = run(second, range(230, 400))
    pw = np.array([c.predicted_um for c in whole[200:]])
    pa = np.array([c.predicted_um for c in after])
    np.testing.assert_allclose(pa, pw, rtol=0, atol=1e-9)  # the same model state: the same predictions
    assert not any(c.flags & Flags.COLD for c in after)
    # a cold start at the same moment takes the warm machine as its zero: off by the warm-up (~2.7 K of nut)
    cold = run(logic(model), range(230, 400))
    assert abs(cold[5].predicted_um - whole[205].predicted_um) > 5.0


def test_cold_when_the_gap_is_long_or_the_machine_changed(seed001_exports, tmp_path):
    model = seed001_exports / "mlr"
    first = logic(model)
    run(first, range(100))
    header, rows = first.state(), np.array(first.stepped)
    lg = logic(model)
    now = {k: r.value for k, r in readings(100).items()}
    assert lg.resume_decision(header, rows, T0 + 99 + 61, now) == (
        False, "the saved state is 61 s old, more than the 60 s the runtime bridges")
    hot = {**now, "T_nut_C": now["T_nut_C"] + 2.5}
    ok, why = lg.resume_decision(header, rows, T0 + 110, hot)
    assert not ok and why.startswith("T_nut is ") and "more than 2.0 K apart" in why
    assert lg.resume_decision(header, rows, T0 + 50, now)[1].startswith("machine time went back")
    other = {**header, "temperatures": ["T_nut"]}
    assert lg.resume_decision(other, rows, T0 + 110, now) == (False, "the saved state is of another model")
    # a gap the runtime does not bridge, inside a run: restarted cold, flagged COLD from then on
    cs = run(first, [*range(100, 110), *range(200, 230)])
    assert cs[10].flags & Flags.RESTARTED and all(c.flags & Flags.COLD for c in cs[10:])
    assert not any(c.flags & Flags.COLD for c in cs[:10])


def test_state_files_are_checked(tmp_path, seed001_exports):
    from thermbench.outputs import OutputRefused

    (tmp_path / "state.json").write_text("{}")  # a user's file of that name: never read as a state, nor replaced
    with pytest.raises(OutputRefused, match=r"state.json: exists and thermbench did not write it"):
        StateStore(tmp_path / "state.json")
    # a state whose samples are not its own (a power cut after the samples were cut short): a loud
    # cold start, not a refusal
    first = logic(seed001_exports / "mlr")
    run(first, range(50))
    store = StateStore(tmp_path / "s2.json")
    store.sync(first.stepped, first.starts)
    store.save(first.state())  # the process dies here: the samples stream is never closed
    samples = tmp_path / "s2.json.samples.csv"
    samples.write_text("\n".join(samples.read_text().splitlines()[:30]) + "\n")
    header, rows = StateStore(tmp_path / "s2.json").load()
    ok, why = logic(seed001_exports / "mlr").resume_decision(header, rows, T0 + 55, {k: r.value for k, r in readings(55).items()})
    assert not ok and why.startswith("the saved state is inconsistent (s2.json.samples.csv has 30 rows"), why
