"""What limits a held-out score (thermbench/evidence.py): each piece of evidence checked
against a hand count or the noise a test planted, and the verdict the report gives."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from thermbench.bench.evidence import error_scatter_um, held_out_limits, outside_training_range
from thermbench.bench.splits import Fold


class _Data:
    """The few parts of a Dataset the evidence reads: the process log, its sensor and operating
    columns, and an errors table that already carries ``thermal_um``."""

    def __init__(self, process: dict[str, pd.DataFrame], errors: pd.DataFrame | None = None):
        self.process = pd.concat([p.assign(run_id=r) for r, p in process.items()], ignore_index=True)
        self.sensor_columns = ["t1_C", "t2_C"]
        self.metadata = SimpleNamespace(operating_inputs=lambda: ["spindle_rpm"])
        self.errors = errors if errors is not None else pd.DataFrame(columns=["run_id", "t_s", "thermal_um", "cycle"])

    def process_run(self, run):
        return self.process[self.process["run_id"] == run].reset_index(drop=True)


def _log(t1, t2, rpm):
    return pd.DataFrame({"t_s": np.arange(len(t1)) * 60.0, "t1_C": t1, "t2_C": t2, "spindle_rpm": rpm})


def test_outside_the_training_range_against_a_hand_count():
    ds = _Data({
        "a": _log([20, 21, 22], [30, 30.5, 31], [0, 1000, 1000]),      # rises t1 0..2, t2 0..1
        "b": _log([25, 25.5, 26], [30, 30, 30], [2000, 2000, 0]),      # rises t1 0..1, t2 0; rpm 0..2000
        "new": _log([20, 21, 23, 23.5], [30, 30.2, 30.4, 30.9], [500, 500, 500, 500]),
    })  # fmt: skip
    r = outside_training_range(ds, ["a", "b"], ["new"])
    # held-out t1 rises 0, 1, 3, 3.5: two of four readings above the training range's 2 (by up to 1.5 °C);
    # t2 rises up to 0.9 stay within 0..1, rpm 500 within 0..2000
    assert r["share"] == 0.5
    assert (r["input"], r["excursion"], r["span"]) == ("t1_C rise", 1.5, 2.0)
    inside = outside_training_range(ds, ["a", "b", "new"], ["a"])
    assert inside == {"share": 0.0, "input": "", "excursion": 0.0, "span": 0.0}


def test_an_operating_signal_below_every_training_value_is_named():
    ds = _Data({"a": _log([20, 21], [30, 31], [3000, 4000]), "b": _log([20, 20.5], [30, 30.5], [2500, 3500]),
                "tail": _log([20, 20.2], [30, 30.1], [500, 2500])})  # fmt: skip
    r = outside_training_range(ds, ["a", "b"], ["tail"])
    assert r["share"] == 0.5 and r["input"] == "spindle_rpm" and r["excursion"] == -2000.0 and r["span"] == 1500.0


def test_the_error_scatter_finds_the_planted_noise_under_a_drift():
    """A slow drift (60 µm over the run, curved) plus white noise of known σ at each of three
    targets: the second differences see the noise, not the drift."""
    rng = np.random.default_rng(7)
    rows = []
    for run, sigma in (("r1", 0.2), ("r2", 0.25), ("r3", 0.3)):
        t = np.arange(4000) * 15.0
        for target in (0.0, 100.0, 200.0):
            drift = 60 * (1 - np.exp(-t / 20000.0)) * (1 + target / 200)
            rows.append(pd.DataFrame({"run_id": run, "t_s": t, "target_mm": target, "cycle": np.arange(t.size),
                                      "thermal_um": drift + rng.normal(0, sigma, t.size)}))  # fmt: skip
    ds = _Data({"r1": _log([20], [30], [0])}, pd.concat(rows, ignore_index=True))
    assert error_scatter_um(ds, ["r1", "r2", "r3"]) == pytest.approx(0.25, rel=0.05)  # the median run's σ
    assert error_scatter_um(ds, ["r1"]) == pytest.approx(0.2, rel=0.05)
    assert np.isnan(error_scatter_um(ds, ["nothing"]))


def _summary(choice, base):
    return pd.DataFrame([{"case": "d", "chosen_median_rmse_um": choice, "baseline_median_rmse_um": base}])


def test_the_verdict_names_the_ratio_to_the_baseline_and_the_evidence():
    rng = np.random.default_rng(1)
    t = np.arange(300) * 15.0
    errors = pd.DataFrame({"run_id": "new", "t_s": t, "target_mm": 0.0, "cycle": np.arange(t.size),
                           "thermal_um": rng.normal(0, 1.0, t.size)})  # fmt: skip
    ds = _Data({"a": _log([20, 22], [30, 31], [0, 0]), "new": _log([20, 25, 24], [30, 30, 30], [0, 0, 0])}, errors)
    folds = [Fold("new", ("a",), ("new",))]
    nested = pd.DataFrame({"case": ["d"], "inner_median_rmse_um": [0.5]})
    # better than the baseline: the ratio, and still the evidence the data hold
    (met,) = held_out_limits(_summary(1.5, 2.0), {"d": (ds, folds)}, nested).to_dict("records")
    assert met["ratio"] == pytest.approx(0.75) and met["verdict"].startswith("choice 1.50 µm, 0.75× the best baseline's 2.00 µm; ")
    # missed: every piece of evidence is there (the baseline 1.1 within 1.25 x the planted σ of 1 µm; two
    # of three readings above t1's training range, by 3 °C; held out 3 x the inner CV)
    (row,) = held_out_limits(_summary(1.5, 1.1), {"d": (ds, folds)}, nested).to_dict("records")
    assert row["ratio"] == pytest.approx(1.5 / 1.1) and row["outside_range_worst"] == pytest.approx(2 / 3) and row["worst_fold"] == "new"
    assert row["furthest_input"] == "t1_C rise" and row["excursion"] == 3.0
    v = row["verdict"]
    assert v.startswith("choice 1.50 µm, 1.36× the best baseline's 1.10 µm; ")
    assert "what is left is mostly measurement noise" in v
    assert "67% of the readings of held-out fold new lie outside the training runs' range (furthest: t1_C rise, 3 °C above it)" in v
    assert "inner cross-validation median 0.50 µm, held out 1.50 µm" in v
    # missed with no limit in the data: said so, not left blank
    quiet = _Data({"a": _log([20, 25], [30, 31], [0, 0]), "new": _log([20, 21], [30, 30.5], [0, 0])}, errors)
    (row,) = held_out_limits(_summary(3.3, 3.0), {"d": (quiet, folds)}, nested.assign(inner_median_rmse_um=2.5)).to_dict("records")
    assert "no limit found in the data" in row["verdict"] and row["verdict"].endswith("the families fall short")
    # better than the baseline with nothing found: the ratio alone
    (row,) = held_out_limits(_summary(2.7, 3.0), {"d": (quiet, folds)}, nested.assign(inner_median_rmse_um=2.5)).to_dict("records")
    assert row["verdict"] == "choice 2.70 µm, 0.90× the best baseline's 3.00 µm"


def test_only_the_span_a_run_is_scored_on_counts():
    """A segment that keeps its history (fl_thermal's tail) has a log from the test's start: its
    rises count from there, but only the readings from its first to its last error reading are
    held-out readings."""
    errors = pd.DataFrame({"run_id": ["a", "a", "h", "h"], "t_s": [0.0, 120.0, 120.0, 180.0], "thermal_um": 0.0,
                           "cycle": [0, 1, 0, 1]})  # fmt: skip
    # h's log: a rise of 5 °C at 60 s (history, not scored), then back within a's 0..2
    ds = _Data({"a": _log([20, 21, 22], [30, 30, 30], [0, 0, 0]), "h": _log([20, 25, 21.5, 21.8], [30] * 4, [0] * 4)},
               errors)  # fmt: skip
    assert outside_training_range(ds, ["a"], ["h"])["share"] == 0.0
    # scored from 60 s: one of its three readings (the 5 °C rise) is outside, by 3 °C
    ds.errors = pd.concat([errors, errors.iloc[[2]].assign(t_s=60.0)], ignore_index=True)
    r = outside_training_range(ds, ["a"], ["h"])
    assert r["share"] == pytest.approx(1 / 3) and (r["input"], r["excursion"]) == ("t1_C rise", 3.0)


def test_the_report_gives_the_verdict_and_the_evidence_table(tmp_path):
    from thermbench.report import write_report

    rows = [{"dataset": "d", "channel": "all", "family": fam, "approach": "global", "kind": "validation", "fold": f,
             "run_id": f, "train": "all", "own": False, "rmse_um": v, "rms_error_um": 5.0, "compensation_rate": 0.5,
             "max_abs_residual_um": 2 * v}
            for f in ("r1", "r2") for fam, v in (("lssvm", 1.0), ("baseline_ridge", 1.1))]  # fmt: skip
    limits = pd.DataFrame([{"case": "d", "choice_median_um": 1.0, "baseline_median_um": 1.1, "ratio": 1.0 / 1.1,
                            "outside_range_median": 0.25, "outside_range_worst": 0.5, "worst_fold": "r2",
                            "furthest_input": "t1_C rise", "excursion": 1.5, "scatter_um": 0.9,
                            "inner_cv_median_um": 0.6, "verdict": "choice 1.00 µm: because"}])  # fmt: skip
    md = write_report(pd.DataFrame(rows), None, tmp_path / "rep", reference=["baseline_ridge"], limits=limits).read_text()
    section = md[md.index("### What limits the held-out error"):md.index("## The run")]
    assert "- **d**: choice 1.00 µm: because" in section and "target" not in section
    lines = [[c.strip() for c in ln.strip("|").split("|")] for ln in section.splitlines() if ln.startswith("|")]
    assert lines[0][:4] == ["case", "choice median µm", "best baseline µm", "ratio"]
    assert lines[2][:4] == ["d", "1.00", "1.10", "0.91×"]
