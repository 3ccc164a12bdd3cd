"""The benchmark's answer in one screen (thermbench/report/answer.py): the figures against a hand count on a
results table made here, the same figures in the report's first screen, the terminal text and the
MLflow metric names."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from thermbench import bench as bm
from thermbench.report import write_report
from thermbench.report.answer import ANSWER_HEADERS, answer_markdown, answer_metrics, answer_table, answer_text

BASELINES = ["baseline_ridge", "baseline_ols"]


def _results():
    """Three folds of one held-out run each; the choice (lssvm, mlp in r2) with a 90 % interval of
    coverage 0.8 / 1.0 / 0.9 and half-widths 2, 4, 3 µm; every family also as deployed, 0.5 µm
    worse (0.6 µm), and in r2 a sensor judged faulty."""
    rows = []
    for fold, (lssvm, ridge, ols, none, cov, hw) in {"r1": (1.0, 2.0, 3.0, 10.0, 0.8, 2.0),
                                                      "r2": (3.0, 2.5, 3.5, 12.0, 1.0, 4.0),
                                                      "r3": (1.5, 1.0, 2.0, 1.2, 0.9, 3.0)}.items():  # fmt: skip
        for fam, v in (("lssvm", lssvm), ("mlp", lssvm + 0.25), ("baseline_ridge", ridge), ("baseline_ols", ols)):
            rows.append({"dataset": "d", "channel": "all", "family": fam, "approach": "global", "kind": "validation",
                         "fold": fold, "run_id": fold, "train": "all", "own": False, "rmse_um": v, "rms_error_um": none,
                         "compensation_rate": 0.5, "max_abs_residual_um": 2 * v, "coverage_90": cov,
                         "half_width_um": hw})  # fmt: skip
            rows.append(rows[-1] | {"approach": "as_deployed", "rmse_um": v + 0.6, "coverage_90": np.nan,
                                    "half_width_um": np.nan, "faults": "t5: range at 7200 s" if fold == "r2" else ""})
    choice = pd.DataFrame({"case": "d", "fold": ["r1", "r2", "r3"], "family": ["lssvm", "mlp", "lssvm"],
                           "approach": "global"})  # fmt: skip
    return pd.DataFrame(rows), choice


def test_the_answer_against_a_hand_count():
    results, choice = _results()
    held = bm.held_out_summary(results, choice, BASELINES)
    # the choice's RMSE per fold 1.0, 3.25, 1.5: median 1.5, worst 3.25; ridge 2.0, 2.5, 1.0: median 2.0;
    # no compensation 10, 12, 1.2: median 10; coverage (0.8 + 1.0 + 0.9) / 3, half-width (2 + 4 + 3) / 3
    (row,) = held.to_dict("records")
    assert row["chosen_coverage"] == pytest.approx(0.9) and row["chosen_half_width_um"] == pytest.approx(3.0)
    # as deployed: 1.6, 3.85, 2.1 (the folds' choices + 0.6): median 2.1, worst 3.85; the faulty run of mlp's fold
    assert row["chosen_deployed_median_rmse_um"] == pytest.approx(2.1) and row["chosen_deployed_worst_rmse_um"] == pytest.approx(3.85)
    assert row["chosen_faults"] == "r2: t5: range at 7200 s"
    deployed = pd.DataFrame({"case": ["d"], "family": ["lssvm"], "approach": ["bank"]})
    (a,) = answer_table(held, deployed).to_dict("records")
    assert (a["deploy"], a["folds"], a["median_um"], a["worst_um"], a["deployed_um"]) == ("lssvm (bank)", 3, 1.5, 3.25, pytest.approx(2.1))
    assert (a["baseline"], a["baseline_um"], a["none_um"]) == ("baseline_ridge", 2.0, 10.0)
    assert a["ratio"] == pytest.approx(0.75) and a["coverage"] == pytest.approx(0.9)
    m = answer_metrics(answer_table(held, deployed), 0.9)
    assert m == pytest.approx({"d/held_out_median_rmse_um": 1.5, "d/held_out_worst_rmse_um": 3.25,
                               "d/as_deployed_median_rmse_um": 2.1,
                               "d/best_baseline_median_rmse_um": 2.0, "d/ratio_to_best_baseline": 0.75,
                               "d/uncompensated_median_rmse_um": 10.0, "d/interval_coverage_90": 0.9,
                               "d/interval_half_width_um": 3.0})  # fmt: skip
    text = answer_text(answer_table(held, deployed), 0.9)
    line = next(ln for ln in text.splitlines() if ln.startswith("d "))
    assert line.split() == ["d", "lssvm", "(bank)", "1.50", "3.25", "2.10", "2.00", "0.75×", "10.00", "90", "%", "3.00"]
    assert "- d as deployed: a sensor judged faulty on held-out r2: t5: range at 7200 s" in text


def test_without_intervals_or_a_choice_the_cells_say_so():
    results, choice = _results()
    held = bm.held_out_summary(results.drop(columns=["coverage_90", "half_width_um"]), choice.iloc[:0], BASELINES)
    a = answer_table(held, pd.DataFrame(columns=["case", "family", "approach"]))
    assert a.loc[0, "deploy"] == "-" and np.isnan(a.loc[0, "median_um"]) and np.isnan(a.loc[0, "coverage"])
    assert set(answer_metrics(a, 0.9)) == {"d/best_baseline_median_rmse_um", "d/uncompensated_median_rmse_um"}


def test_the_report_opens_with_the_answer_in_one_screen(tmp_path):
    """Five cases (a dataset of five channels): the table, the figure and the notes come first, in
    under 40 lines, each header cell one short value."""
    results, choice = _results()
    many = pd.concat([results.assign(channel=f"ch{k}") for k in range(1, 6)], ignore_index=True)
    choices = pd.concat([choice.assign(case=f"d-ch{k}") for k in range(1, 6)], ignore_index=True)
    held = bm.held_out_summary(many, choices, BASELINES)
    answer = answer_table(held, choices.drop_duplicates("case").assign(approach="global"))
    path = write_report(many, None, tmp_path / "rep", reference=BASELINES, answer=answer, level=0.9)
    md = path.read_text(encoding="utf-8").splitlines()
    screen = md[: md.index("## The run")]
    assert len(screen) < 40 and screen[0] == "# Thermal-error robustness report"
    header = [c.strip() for c in screen[2].strip("|").split("|")]
    assert header == list(ANSWER_HEADERS.values()) and max(map(len, header)) <= 20
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in screen[4:9]]
    assert [r[0] for r in rows] == [f"d-ch{k}" for k in range(1, 6)]
    assert rows[0][1:] == ["lssvm", "1.50", "3.25", "2.10", "2.00", "0.75×", "10.00", "90 %", "3.00"]
    assert "![held-out RMSE per dataset and channel](figures/summary.png)" in screen
    png = tmp_path / "rep" / "figures" / "summary.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    first = ["# Thermal-error robustness report", ""] + answer_markdown(answer, 0.9, "figures/summary.png")
    assert "\n".join(screen) == "\n".join(first)


def test_the_held_out_table_gives_every_model_its_interval(tmp_path):
    """Coverage and half-width per model: the means over the folds (here lssvm 0.8, 1.0, 0.9 and
    2, 4, 3 µm on its three folds: 0.9 and 3.0), none for no compensation; in the report's section."""
    results, choice = _results()
    results.loc[results["family"] == "baseline_ols", ["coverage_90", "half_width_um"]] = [0.5, 1.0]
    t = bm.held_out_table(results, choice, BASELINES).set_index("model")
    assert t.loc["lssvm (global)", "coverage"] == pytest.approx(0.9) and t.loc["lssvm (global)", "half_width_um"] == 3.0
    assert (t.loc["baseline_ols (global) (baseline)", "coverage"], t.loc["baseline_ols (global) (baseline)", "half_width_um"]) == (0.5, 1.0)
    assert np.isnan(t.loc["no compensation", "coverage"]) and np.isnan(t.loc["no compensation", "half_width_um"])
    md = write_report(results, None, tmp_path / "rep", reference=BASELINES,
                      held_out=bm.held_out_table(results, choice, BASELINES)).read_text(encoding="utf-8")
    section = md[md.index("## Held out"):md.index("## The run")]
    lines = [[c.strip() for c in ln.strip("|").split("|")] for ln in section.splitlines() if ln.startswith("|")]
    assert lines[0][-2:] == ["interval covers", "± µm"]
    assert next(ln for ln in lines if ln[0] == "baseline_ols (global) (baseline)")[-2:] == ["50 %", "1.00"]
    assert next(ln for ln in lines if ln[0] == "no compensation")[-2:] == ["—", "—"]
