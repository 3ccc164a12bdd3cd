"""The robustness report: tables from hand-set metrics, the markdown/PNG output and
its atomic write.

Every expected number below is computed by hand from the literal tables in this
file (the arithmetic is in the comments), never read back from the code.
"""

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from thermbench.outputs import RECORD
from matplotlib.figure import Figure

from thermbench import report
from thermbench.report import (
    approach_comparison,
    figure_paths,
    headline,
    markdown_table,
    terminal_summary,
    train_test_matrix,
    write_report,
)

STATES = ["s1", "s2", "s3"]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

# dsA / mlr / single: rate and max residual (µm), rows = training state, columns = test run
MLR_RATE = {
    "s1": {"s1": 0.90, "s2": 0.40, "s3": -0.50, "v1": 0.60, "v2": 0.20},
    "s2": {"s1": 0.30, "s2": 0.85, "s3": 0.20, "v1": 0.50, "v2": 0.70},
    "s3": {"s1": -1.50, "s2": 0.10, "s3": 0.95, "v1": -0.25, "v2": 0.40},
}
MLR_RES = {
    "s1": {"s1": 1.11, "s2": 6.00, "s3": 15.00, "v1": 4.00, "v2": 8.00},
    "s2": {"s1": 7.00, "s2": 1.50, "s3": 8.00, "v1": 5.00, "v2": 3.00},
    "s3": {"s1": 25.00, "s2": 9.00, "s3": 0.50, "v1": 12.50, "v2": 6.00},
}
# dsA / mlr / global and bank (trained on all states): (rate, max residual µm)
MLR_ALL = {
    "global": {"s1": (0.80, 2.0), "s2": (0.82, 1.9), "s3": (0.78, 2.2), "v1": (0.55, 4.40), "v2": (0.65, 3.30)},
    "bank": {"s1": (0.88, 1.2), "s2": (0.86, 1.4), "s3": (0.90, 1.0), "v1": (0.70, 2.20), "v2": (0.45, 5.05)},
}


def _row(ds, fam, app, train, run, own, rate, res):
    kind = "state" if run.startswith("s") else "validation"
    max_err = 40.0
    return {
        "dataset": ds,
        "family": fam,
        "approach": app,
        "train": train,
        "run_id": run,
        "kind": kind,
        "own": own,
        "rmse_um": res / 2,
        "max_abs_residual_um": res,
        "pv_residual_um": res * 1.5,
        "max_abs_error_um": max_err,
        "pv_error_um": max_err,
        "compensation_rate": rate,
        "residual_fraction_of_pv": res / max_err,
        "fit_s": 0.1,
    }


def _results():
    rows = []
    # dsA: the hand-set mlr tables; physics single-state only, on a simple pattern
    for tr, cells in MLR_RATE.items():
        for run, rate in cells.items():
            rows.append(_row("dsA", "mlr", "single", tr, run, run == tr, rate, MLR_RES[tr][run]))
    for app, cells in MLR_ALL.items():
        for run, (rate, res) in cells.items():
            rows.append(_row("dsA", "mlr", app, "all", run, run.startswith("s"), rate, res))
    for i, tr in enumerate(STATES):
        for j, run in enumerate(STATES + ["v1", "v2"]):
            rows.append(_row("dsA", "physics", "single", tr, run, run == tr, 0.9 - 0.05 * abs(i - j), 1.0 + abs(i - j)))
    # dsB: other validation runs (w1, w2), both families, all approaches
    for f, fam in enumerate(["mlr", "physics"]):
        for i, tr in enumerate(STATES):
            for j, run in enumerate(STATES + ["w1", "w2"]):
                rows.append(_row("dsB", fam, "single", tr, run, run == tr, 0.7 - 0.1 * abs(i - j) - 0.1 * f, 2.0 + j))
        for app in ["global", "bank"]:
            for j, run in enumerate(STATES + ["w1", "w2"]):
                rows.append(_row("dsB", fam, app, "all", run, run.startswith("s"), 0.6 + 0.05 * j, 3.0))
    return pd.DataFrame(rows)


def _curves():
    t_s = np.arange(0.0, 4 * 3600.0 + 1, 1800.0)
    rows = []
    for ds, runs, lines in [
        ("dsA", ["v1", "v2"], [("mlr", "global"), ("mlr", "bank"), ("physics", "single")]),
        ("dsB", ["w1", "w2"], [("mlr", "global"), ("physics", "bank")]),
    ]:
        for k, run in enumerate(runs):
            before = 5.0 + (k + 1) * 8.0 * (1 - np.exp(-t_s / 5000.0))
            for m, (fam, app) in enumerate(lines):
                for t, b in zip(t_s, before):
                    rows.append({"dataset": ds, "family": fam, "approach": app, "run_id": run, "t_s": t,
                                 "before_um": b, "after_um": 0.1 * (m + 1) * b})
    return pd.DataFrame(rows)


@pytest.fixture(scope="module")
def results():
    return _results()


# ----------------------------------------------------------------------------- tables


def test_matrix_puts_each_value_at_its_train_test_cell(results):
    shuffled = results.sample(frac=1.0, random_state=3)
    for metric, table in [("compensation_rate", MLR_RATE), ("max_abs_residual_um", MLR_RES)]:
        m = train_test_matrix(shuffled, "dsA", "mlr", metric)
        assert sorted(m.index) == STATES and sorted(m.columns) == STATES  # validation runs excluded
        for tr in STATES:
            for te in STATES:
                assert m.loc[tr, te] == pytest.approx(table[tr][te]), (metric, tr, te)
    # in the unshuffled frame the states keep their order of appearance
    m = train_test_matrix(results, "dsA", "mlr")
    assert list(m.index) == STATES and list(m.columns) == STATES
    assert m.index.name == "train" and m.columns.name == "test"
    assert m.loc["s3", "s1"] == pytest.approx(-1.50)


def test_matrix_unknown_family_or_metric_is_a_clear_error(results):
    with pytest.raises(ValueError, match="family 'gru'.*families with single models on 'dsA': \\['mlr', 'physics'\\]"):
        train_test_matrix(results, "dsA", "gru")
    with pytest.raises(ValueError, match="no column 'nope'"):
        train_test_matrix(results, "dsA", "mlr", "nope")


def test_headline_worst_and_mean_match_hand_computation(results):
    h = headline(results)
    s = h.loc[("dsA", "mlr", "single")]
    assert s["n_models"] == 3
    assert s["own_rate_mean"] == pytest.approx(0.90)  # (0.90 + 0.85 + 0.95) / 3
    assert s["val_rate_worst"] == pytest.approx(-0.25)  # s3 model on v1
    # per run, mean over training states: v1 (0.60 + 0.50 - 0.25)/3, v2 (0.20 + 0.70 + 0.40)/3
    assert s["v1:rate"] == pytest.approx(0.85 / 3)
    assert s["v2:rate"] == pytest.approx(1.30 / 3)
    assert s["val_rate_mean"] == pytest.approx(2.15 / 6)
    assert s["v1:residual_um"] == pytest.approx(21.5 / 3)  # (4 + 5 + 12.5) / 3
    assert s["val_worst_residual_um"] == pytest.approx(12.50)
    # off-diagonal: 0.40, -0.50, 0.30, 0.20, -1.50, 0.10
    assert s["states_rate_worst"] == pytest.approx(-1.50)
    assert s["states_rate_mean"] == pytest.approx(-1.0 / 6)
    assert s["states_worst_residual_um"] == pytest.approx(25.0)

    g = h.loc[("dsA", "mlr", "global")]
    assert (g["val_rate_worst"], g["val_rate_mean"], g["val_worst_residual_um"]) == pytest.approx((0.55, 0.60, 4.40))
    assert g["own_rate_mean"] == pytest.approx(0.80)  # (0.80 + 0.82 + 0.78) / 3
    assert np.isnan(g["states_rate_worst"])  # trained on every state: no unseen state
    b = h.loc[("dsA", "mlr", "bank")]
    assert (b["val_rate_worst"], b["val_rate_mean"], b["val_worst_residual_um"]) == pytest.approx((0.45, 0.575, 5.05))
    # dsA rows carry no dsB run columns' values
    assert np.isnan(s["w1:rate"])
    # order: datasets and families as they appear, approaches single, global, bank
    assert list(h.index)[:4] == [("dsA", "mlr", "single"), ("dsA", "mlr", "global"), ("dsA", "mlr", "bank"),
                                 ("dsA", "physics", "single")]


def test_approach_comparison_names_best_and_worst_training_state(results):
    c = approach_comparison(results, "dsA")
    # mean validation rate per training state: s1 0.40, s2 0.60, s3 0.075
    assert c.loc[("mlr", "single best"), "trained_on"] == "s2"
    assert c.loc[("mlr", "single worst"), "trained_on"] == "s3"
    assert c.loc[("mlr", "single worst"), "v1"] == pytest.approx(-0.25)
    assert c.loc[("mlr", "single worst"), "worst_residual_um"] == pytest.approx(12.5)
    assert c.loc[("mlr", "single mean"), "v2"] == pytest.approx(1.30 / 3)
    assert c.loc[("mlr", "bank"), "worst_rate"] == pytest.approx(0.45)
    assert c.loc[("mlr", "global"), "mean_rate"] == pytest.approx(0.60)
    # physics: state i (0..2) on v1 (j=3) / v2 (j=4): 0.9 - 0.05*|i-j|; means s1 0.725, s2 0.775, s3 0.825
    assert c.loc[("physics", "single best"), "trained_on"] == "s3"
    assert c.loc[("physics", "single worst"), "trained_on"] == "s1"
    assert c.loc[("physics", "single worst"), "v1"] == pytest.approx(0.75)


def test_markdown_table_formats_rates_and_micrometres():
    df = pd.DataFrame({"name": ["a|b", "c"], "compensation_rate": [0.8531, -1.5], "x_um": [3.456, np.nan]})
    text = markdown_table(df, index=False)
    assert text.splitlines() == [
        "| name | compensation_rate | x_um |",
        "| --- | ---: | ---: |",
        "| a\\|b | 85.3% | 3.46 |",
        "| c | -150.0% | — |",
    ]


# ----------------------------------------------------------------------------- terminal


def test_terminal_summary_shows_the_worst_numbers(results):
    text = terminal_summary(results)
    lines = text.splitlines()
    assert len(lines) <= 40 and max(map(len, lines)) <= 120
    assert re.search(r"single:val +single:states +global:val +bank:val", text)
    mlr_a = next(line for line in lines if line.startswith("dsA") and " mlr " in line)
    # single: val worst -25 %, mean 35.8 % ((0.2833 + 0.4333)/2), worst 12.50 µm; states -150 %, -16.7 %, 25.00 µm
    assert "-25.0/35.8 12.50" in mlr_a
    assert "-150.0/-16.7 25.00" in mlr_a
    assert "55.0/60.0 4.40" in mlr_a  # global
    assert "45.0/57.5 5.05" in mlr_a  # bank


def test_terminal_summary_fits_one_screen_at_benchmark_size():
    """Four datasets with the real long names, eight families, three approaches,
    nine states and seven validation runs: still one screen."""
    rng = np.random.default_rng(0)
    names = ["seed000_x", "seed001_vmc_x", "seed002_vmc655h_x", "seed004_ff_x"]
    fams = ["mlr_seed001", "mlr_seed002", "mlr_seed004", "lssvm", "mlp", "gru", "ar_seed003", "physics"]
    states = [f"c{i}" for i in range(1, 10)]
    vals = [f"table6_{i}" for i in range(1, 8)]
    rows = []
    for ds in names:
        for fam in fams:
            for app, trains in [("single", states), ("global", ["all"]), ("bank", ["all"])]:
                for tr in trains:
                    for run in states + vals:
                        own = run == tr or (tr == "all" and run in states)
                        rows.append({"dataset": ds, "family": fam, "approach": app, "train": tr, "run_id": run,
                                     "kind": "state" if run in states else "validation", "own": own,
                                     "compensation_rate": rng.uniform(-3.0, 1.0),
                                     "max_abs_residual_um": rng.uniform(0.0, 99.0)})
    lines = terminal_summary(pd.DataFrame(rows)).splitlines()
    assert len(lines) <= 40, len(lines)
    assert max(map(len, lines)) <= 120, max(lines, key=len)


# ----------------------------------------------------------------------------- validation


def test_missing_columns_are_named(results, tmp_path):
    with pytest.raises(ValueError, match=r"results is missing column\(s\) \['own'\]"):
        headline(results.drop(columns=["own"]))
    with pytest.raises(ValueError, match=r"curves is missing column\(s\) \['after_um'\]"):
        write_report(results, _curves().drop(columns=["after_um"]), tmp_path / "out")
    assert not (tmp_path / "out").exists()  # checked before anything is written
    with pytest.raises(ValueError, match="results is empty"):
        terminal_summary(results.iloc[:0])


def test_bad_values_are_rejected(results, tmp_path):
    bad = results.copy()
    bad.loc[0, "kind"] = "test"
    with pytest.raises(ValueError, match=r"'kind' has unexpected value\(s\) \['test'\]"):
        headline(bad)
    dup = pd.concat([results, results.iloc[[0]]])
    with pytest.raises(ValueError, match="sharing \\(dataset, family, approach, train, run_id\\)"):
        headline(dup)
    c = _curves()
    with pytest.raises(ValueError, match="add a 'train' column"):
        write_report(results, pd.concat([c, c.iloc[[0]]]), tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_negative_rate_is_red_and_printed_true():
    """A model that makes things worse (-150 %) shows at the red end of the scale
    (clipped to -100 %) while its label keeps the true value."""
    fig = Figure()
    ax = fig.add_subplot()
    rate = np.array([[-1.5, 0.0, 0.9]])
    im = report._rate_heatmap(fig, ax, rate, [["-150.0%", "0.0%", "90.0%"]], ["t"], ["a", "b", "c"])
    rgba = [im.cmap(im.norm(v)) for v in im.get_array()[0]]
    assert rgba[0][0] > 3 * max(rgba[0][1], rgba[0][2])  # (dark) red
    assert abs(rgba[1][0] - rgba[1][2]) < 0.05 and min(rgba[1][:3]) > 0.9  # white-ish centre
    assert rgba[2][2] > rgba[2][0]  # blue
    assert im.get_array()[0][0] == pytest.approx(-1.0)
    assert [t.get_text() for t in ax.texts] == ["-150.0%", "0.0%", "90.0%"]


# ----------------------------------------------------------------------------- report


def _referenced_pngs(text):
    return re.findall(r"\]\((figures/[^)]+\.png)\)", text)


def test_write_report_layout_values_and_figures(results, tmp_path):
    meta = {"command": "thermbench robustness --all", "git_commit": "abc1234", "wall_time_s": "12.3"}
    path = write_report(results, _curves(), tmp_path / "out", meta=meta)
    assert path == tmp_path / "out" / "report.md"
    text = path.read_text(encoding="utf-8")
    assert "`thermbench robustness --all`" in text and "abc1234" in text
    assert "How to read this report" in text
    # dsA mlr single headline row, hand-computed above, formatted % (1 decimal) and µm (2 decimals)
    row = next(line for line in text.splitlines() if line.startswith("| mlr | single | 3 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells == ["mlr", "single", "3", "90.0%", "-25.0%", "35.8%", "12.50", "-150.0%", "-16.7%", "25.00",
                     "28.3% / 7.17", "43.3% / 5.67"]
    assert "| mlr | global | 1 | 80.0% | 55.0% | 60.0% | 4.40 |" in text
    # comparison table: the worst single mlr model was trained on s3 and got -25 % on v1
    assert re.search(r"\| mlr \| single worst \| s3 \| -25\.0% \| 40\.0% \| 7\.5% \| -25\.0% \| 12\.50 \|", text)
    # matrix summary: off-diagonal worst -150 % (trained on s3, tested on s1)
    assert "worst -150.0% (trained on s3, tested on s1)" in text
    refs = _referenced_pngs(text)
    # 2 comparisons + 4 matrices (2 datasets x 2 families) + 2 before/after
    assert len(refs) == 8 and len(set(refs)) == 8
    on_disk = figure_paths(tmp_path / "out")
    assert sorted(tmp_path / "out" / r for r in refs) == on_disk
    for p in on_disk:
        data = p.read_bytes()
        assert data[:8] == PNG_MAGIC and len(data) > 5000, p
    assert [p.name for p in (tmp_path / "out").rglob(".*")] == [RECORD]  # no temporary leftovers


def test_report_without_curves_says_so(results, tmp_path):
    results = results[results["dataset"] == "dsA"]
    path = write_report(results, None, tmp_path)
    text = path.read_text(encoding="utf-8")
    assert text.count("_No before/after curves for this dataset's validation runs._") == 1
    assert [p.name for p in figure_paths(tmp_path)] == ["compare__dsA.png", "matrix__dsA__mlr.png",
                                                         "matrix__dsA__physics.png"]
    empty = write_report(results, pd.DataFrame(), tmp_path / "empty").read_text(encoding="utf-8")
    assert empty == text


def test_failed_figure_leaves_previous_report_intact(results, tmp_path, monkeypatch):
    results = results[results["dataset"] == "dsA"]  # one dataset keeps the test fast
    out = tmp_path / "out"
    write_report(results, _curves(), out, meta={"command": "first"})
    before_text = (out / "report.md").read_bytes()
    before_figs = {p.name: p.read_bytes() for p in figure_paths(out)}

    def boom(*args, **kwargs):
        raise RuntimeError("injected plotting failure")

    monkeypatch.setattr(report, "curves_figure", boom)
    with pytest.raises(RuntimeError, match="injected"):
        write_report(results.assign(compensation_rate=0.0), _curves(), out, meta={"command": "second"})
    assert (out / "report.md").read_bytes() == before_text
    assert {p.name: p.read_bytes() for p in figure_paths(out)} == before_figs
    assert sorted(p.name for p in out.iterdir()) == [RECORD, "figures", "report.md"]

    fresh = tmp_path / "fresh"
    with pytest.raises(RuntimeError, match="injected"):
        write_report(results, _curves(), fresh)
    assert not fresh.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging left behind


def test_failed_text_write_leaves_previous_report_intact(results, tmp_path, monkeypatch):
    """A disk-full in the middle of writing report.md: the old report stays whole."""
    results = results[results["dataset"] == "dsA"]
    write_report(results, None, tmp_path, meta={"command": "first"})
    before = (tmp_path / "report.md").read_bytes()
    real_write_text = Path.write_text

    def half_then_fail(self, data, *args, **kwargs):
        real_write_text(self, data[: len(data) // 2], *args, **kwargs)
        raise OSError("No space left on device")

    monkeypatch.setattr(Path, "write_text", half_then_fail)
    with pytest.raises(OSError, match="No space left"):
        write_report(results, None, tmp_path, meta={"command": "second"})
    monkeypatch.undo()
    assert (tmp_path / "report.md").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [RECORD, "figures", "report.md"]
