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
from thermbench.bench import results as bench_results
from thermbench.report import details, figures, markdown, tables
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
    lines = text.splitlines()
    assert len(lines) == 4 and all(ln.startswith("|") and ln.endswith("|") for ln in lines)

    def cells(line: str) -> list[str]:  # split on unescaped pipes
        return [c.strip().replace("\x00", "\\|") for c in line.replace("\\|", "\x00").strip("|").split("|")]

    assert cells(lines[0]) == ["name", "compensation_rate", "x_um"]
    # GitHub alignment row: text left, numbers right
    align = cells(lines[1])
    assert align[0].startswith(":") and not align[0].endswith(":")
    assert all(a.endswith(":") and not a.startswith(":") for a in align[1:]) and all(set(a) <= {"-", ":"} for a in align)
    assert cells(lines[2]) == ["a\\|b", "85.3%", "3.46"]
    assert cells(lines[3]) == ["c", "-150.0%", "—"]
    assert len({len(ln) for ln in lines}) == 1  # padded to one width: readable as plain text too


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
    im = figures._rate_heatmap(fig, ax, rate, [["-150.0%", "0.0%", "90.0%"]], ["t"], ["a", "b", "c"])
    rgba = [im.cmap(im.norm(v)) for v in im.get_array()[0]]
    assert rgba[0][0] > 3 * max(rgba[0][1], rgba[0][2])  # (dark) red
    assert abs(rgba[1][0] - rgba[1][2]) < 0.05 and min(rgba[1][:3]) > 0.9  # white-ish centre
    assert rgba[2][2] > rgba[2][0]  # blue
    assert im.get_array()[0][0] == pytest.approx(-1.0)
    assert [t.get_text() for t in ax.texts] == ["-150.0%", "0.0%", "90.0%"]


# ----------------------------------------------------------------------------- report


def compact(text: str) -> str:
    """``text`` with its markdown table rows written with one space around each cell: the rows
    compare as cells, whatever padding the table writer adds for plain-text readability."""
    out = []
    for line in text.splitlines():
        if line.startswith("|") and line.endswith("|"):
            cells = [c.strip().replace("\x00", "\\|") for c in line.replace("\\|", "\x00")[1:-1].split("|")]
            line = "| " + " | ".join(cells) + " |"
        out.append(line)
    return "\n".join(out)


def _referenced_pngs(text):
    return re.findall(r"\]\((figures/[^)]+\.png)\)", text)


def test_write_report_layout_values_and_figures(results, tmp_path):
    meta = {"command": "thermbench robustness --all", "git_commit": "abc1234", "wall_time_s": "12.3"}
    path = write_report(results, _curves(), tmp_path / "out", meta=meta)
    assert path == tmp_path / "out" / "report.md"
    head = compact(path.read_text(encoding="utf-8"))
    assert "`thermbench robustness --all`" in head and "abc1234" in head
    assert "[details.md](details.md)" in head and "[results.csv](results.csv)" in head
    assert "How to read this report" not in head and "figures/" not in head  # the details are linked
    text = compact((path.parent / "details.md").read_text(encoding="utf-8"))
    assert "How to read this report" in text and "[report.md](report.md)" in text
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


def test_figures_drawn_in_two_processes_equal_those_drawn_in_one(results, tmp_path):
    """n_jobs=2 draws the figures in other processes: the same report and the same PNGs, byte for byte."""
    one = write_report(results, _curves(), tmp_path / "one", meta={"command": "x"})
    two = write_report(results, _curves(), tmp_path / "two", meta={"command": "x"}, n_jobs=2)
    for name in ("report.md", "details.md"):
        assert (two.parent / name).read_text(encoding="utf-8") == (one.parent / name).read_text(encoding="utf-8")
    pngs = figure_paths(tmp_path / "one")
    assert len(pngs) == 8 and [p.name for p in figure_paths(tmp_path / "two")] == [p.name for p in pngs]
    for p in pngs:
        assert (tmp_path / "two" / "figures" / p.name).read_bytes() == p.read_bytes(), p.name


def test_report_without_curves_says_so(results, tmp_path):
    results = results[results["dataset"] == "dsA"]
    path = write_report(results, None, tmp_path)
    text = (path.parent / "details.md").read_text(encoding="utf-8")
    assert text.count("_No before/after curves for this dataset's validation runs._") == 1
    assert [p.name for p in figure_paths(tmp_path)] == ["compare__dsA.png", "matrix__dsA__mlr.png",
                                                         "matrix__dsA__physics.png"]
    write_report(results, pd.DataFrame(), tmp_path / "empty")
    assert (tmp_path / "empty" / "details.md").read_text(encoding="utf-8") == text


def test_failed_figure_leaves_previous_report_intact(results, tmp_path, monkeypatch):
    results = results[results["dataset"] == "dsA"]  # one dataset keeps the test fast
    out = tmp_path / "out"
    write_report(results, _curves(), out, meta={"command": "first"})
    before_text = (out / "report.md").read_bytes()
    before_figs = {p.name: p.read_bytes() for p in figure_paths(out)}
    before_csv = (out / "results.csv").read_bytes()

    def boom(*args, **kwargs):
        raise RuntimeError("injected plotting failure")

    monkeypatch.setattr(details, "curves_figure", boom)  # where write_report's sections look it up
    with pytest.raises(RuntimeError, match="injected"):
        write_report(results.assign(compensation_rate=0.0), _curves(), out, meta={"command": "second"})
    assert (out / "report.md").read_bytes() == before_text
    assert {p.name: p.read_bytes() for p in figure_paths(out)} == before_figs
    assert (out / "results.csv").read_bytes() == before_csv
    assert sorted(p.name for p in out.iterdir()) == [RECORD, "details.md", "figures", "report.md", "results.csv"]

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
    assert sorted(p.name for p in tmp_path.iterdir()) == [RECORD, "details.md", "figures", "report.md", "results.csv"]


# ----------------------------------------------------------------------------- several error channels
#
# dataset "spin": modelling states a, b and the validation run "tail", two error channels,
# the family "fam" and the baseline "base", approaches single (trained on a or b) and global.
# RMSE (µm) per channel, family, model (training state or "global") and test run; every other
# metric follows from it: max |residual| = 2 x RMSE, compensation rate = 1 - RMSE / 10.
SPIN_RMSE = {
    "ch1": {
        "base": {"a": {"a": 0.5, "b": 7.0, "tail": 8.0}, "b": {"a": 6.0, "b": 0.4, "tail": 4.0},
                 "global": {"a": 1.0, "b": 1.2, "tail": 5.0}},
        "fam": {"a": {"a": 0.3, "b": 4.0, "tail": 3.0}, "b": {"a": 2.0, "b": 0.2, "tail": 5.0},
                "global": {"a": 0.6, "b": 0.7, "tail": 2.5}},
    },
    "ch2": {
        "base": {"a": {"a": 0.5, "b": 3.0, "tail": 2.0}, "b": {"a": 5.0, "b": 0.6, "tail": 4.0},
                 "global": {"a": 1.5, "b": 1.1, "tail": 6.0}},
        "fam": {"a": {"a": 0.9, "b": 12.0, "tail": 9.0}, "b": {"a": 11.0, "b": 0.8, "tail": 7.0},
                "global": {"a": 2.0, "b": 2.2, "tail": 10.0}},
    },
}
# validation (tail) RMSE, single = mean over the training states a, b:
#            ch1                      ch2
# base single (8 + 4)/2 = 6.00        (2 + 4)/2 = 3.00  <- best of ch2 (a baseline)
# base global 5.00                    6.00
# fam  single (3 + 5)/2 = 4.00        (9 + 7)/2 = 8.00  <- best thermbench of ch2
# fam  global 2.50 <- best of ch1     10.00
CSV_HEAD = ["dataset", "family", "approach", "train", "test", "channel", "rmse_um", "max_abs_residual_um",
            "compensation_rate", "kind", "own", "reference"]


def _spin_results():
    rows = []
    for ch, fams in SPIN_RMSE.items():
        for fam, models in fams.items():
            for model, cells in models.items():
                app, train = ("global", "all") if model == "global" else ("single", model)
                for run, rmse in cells.items():
                    rows.append({"dataset": "spin", "channel": ch, "family": fam, "approach": app, "train": train,
                                 "run_id": run, "kind": "validation" if run == "tail" else "state",
                                 "own": run == model or (model == "global" and run != "tail"),
                                 "rmse_um": rmse, "max_abs_residual_um": 2 * rmse,
                                 "compensation_rate": 1 - rmse / 10, "fit_s": 0.25})
    return pd.DataFrame(rows)


def _spin_curves():
    """Per-cycle before/after on tail for the global models (as the benchmark saves them)."""
    t_s = 1000.0 + 15.0 * np.arange(40)
    rows = []
    for ch in SPIN_RMSE:
        before = 10 + np.sin(t_s / 100.0)
        for m, fam in enumerate(["base", "fam"]):
            rows.append(pd.DataFrame({"dataset": "spin", "channel": ch, "family": fam, "approach": "global",
                                      "train": "all", "run_id": "tail", "t_s": t_s, "before_um": before,
                                      "after_um": 0.2 * (m + 1) * before}))
    return pd.concat(rows, ignore_index=True)


@pytest.fixture(scope="module")
def spin_report(tmp_path_factory):
    """One report of the format 1 dataset dsA beside the two-channel dataset spin (written once)."""
    out = tmp_path_factory.mktemp("spin") / "report"
    mixed = pd.concat([_results().query("dataset == 'dsA'"), _spin_results()], ignore_index=True)
    curves = pd.concat([_curves().query("dataset == 'dsA'"), _spin_curves()], ignore_index=True)
    captured = {}
    real = figures._rmse_heatmap_figure

    def spy(panels, n_states, norm, title, path):
        captured[path.name] = panels
        return real(panels, n_states, norm, title, path)

    mp = pytest.MonkeyPatch()
    mp.setattr(details, "_rmse_heatmap_figure", spy)
    try:
        write_report(mixed, curves, out, reference=["base"])
    finally:
        mp.undo()
    return out, mixed, captured


def test_two_channels_with_the_same_other_keys_are_two_models():
    spin = _spin_results()
    h = headline(spin)  # ch1 and ch2 rows share (dataset, family, approach, train, run_id): accepted
    assert h.index.names == ["dataset", "channel", "family", "approach"]
    assert h.loc[("spin", "ch2", "fam", "global"), "val_rate_worst"] == pytest.approx(0.0)  # 1 - 10/10
    assert h.loc[("spin", "ch1", "fam", "global"), "val_rate_worst"] == pytest.approx(0.75)  # 1 - 2.5/10
    with pytest.raises(ValueError, match=r"sharing \(dataset, family, approach, train, run_id\) and channel"):
        headline(pd.concat([spin, spin.iloc[[0]]]))
    # one channel of a several-channel dataset must be named
    with pytest.raises(ValueError, match=r"several channels \['ch1', 'ch2'\]; pass channel="):
        train_test_matrix(spin, "spin", "fam")
    m = train_test_matrix(spin, "spin", "fam", "rmse_um", channel="ch2")
    assert m.loc["a", "b"] == pytest.approx(12.0) and m.loc["b", "a"] == pytest.approx(11.0)
    c = approach_comparison(spin, "spin", channel="ch1")
    assert c.loc[("fam", "global"), "tail"] == pytest.approx(0.75)
    with pytest.raises(ValueError, match="no channel 'ch9'"):
        approach_comparison(spin, "spin", channel="ch9")


def test_validation_by_channel_and_best_match_hand_computation():
    t = report.validation_by_channel(_spin_results(), "spin")
    assert list(t.columns) == ["ch1", "ch2"]
    assert list(t.index) == [("base", "single"), ("base", "global"), ("fam", "single"), ("fam", "global")]
    expected = {("base", "single"): (6.0, 3.0), ("base", "global"): (5.0, 6.0),
                ("fam", "single"): (4.0, 8.0), ("fam", "global"): (2.5, 10.0)}
    for key, (v1, v2) in expected.items():
        assert (t.at[key, "ch1"], t.at[key, "ch2"]) == pytest.approx((v1, v2)), key
    assert t.attrs["low"].at[("fam", "single"), "ch2"] == pytest.approx(7.0)  # the better state, b
    assert t.attrs["high"].at[("fam", "single"), "ch2"] == pytest.approx(9.0)
    b = report.best_by_channel(t, reference=["base"])
    assert b.loc["ch1", "best"] == ("fam", "global") and b.loc["ch1", "baseline"] == ("base", "global")
    assert (b.loc["ch1", "family_value"], b.loc["ch1", "baseline_value"]) == pytest.approx((2.5, 5.0))
    assert b.loc["ch2", "best"] == ("base", "single")  # a baseline is the best of ch2
    assert b.loc["ch2", "family"] == ("fam", "single")
    assert (b.loc["ch2", "family_value"], b.loc["ch2", "baseline_value"]) == pytest.approx((8.0, 3.0))
    # a single-state model that could not be fitted: mean over the one left, marked (1/2)
    spin = _spin_results()
    gone = (spin["channel"] == "ch2") & (spin["family"] == "fam") & (spin["train"] == "b")
    t = report.validation_by_channel(spin[~gone], "spin")
    assert t.at[("fam", "single"), "ch2"] == pytest.approx(9.0)
    assert t.attrs["n_models"].at[("fam", "single"), "ch2"] == 1
    md = compact(details._channel_table_md(t, frozenset(["base"]), 2, report.fmt_um, lower_is_better=True))
    assert "| fam | single (mean) | 4.00 | 9.00 (1/2) |" in md


def test_results_csv_columns_and_values(spin_report):
    out, mixed, _ = spin_report
    csv = pd.read_csv(out / "results.csv", keep_default_na=False)
    assert list(csv.columns[: len(CSV_HEAD)]) == CSV_HEAD
    assert {"fit_s", "max_abs_error_um"} <= set(csv.columns[len(CSV_HEAD):])
    assert len(csv) == len(mixed)
    row = csv[(csv["dataset"] == "spin") & (csv["channel"] == "ch2") & (csv["family"] == "fam")
              & (csv["approach"] == "global") & (csv["test"] == "tail")]
    assert len(row) == 1
    r = row.iloc[0]
    assert (r["train"], r["kind"], bool(r["own"]), bool(r["reference"])) == ("all", "validation", False, False)
    assert (r["rmse_um"], r["max_abs_residual_um"], r["compensation_rate"]) == pytest.approx((10.0, 20.0, 0.0))
    base = csv[(csv["family"] == "base")]
    assert len(base) == 18 and base["reference"].astype(str).eq("True").all()  # 2 channels x 3 models x 3 runs
    own = csv[(csv["channel"] == "ch1") & (csv["family"] == "base") & (csv["train"] == "b") & (csv["test"] == "b")]
    assert own.iloc[0]["rmse_um"] == pytest.approx(0.4) and str(own.iloc[0]["own"]) == "True"
    # the format 1 rows (no channel column given) are channel "all"
    fmt1 = csv[csv["dataset"] == "dsA"]
    assert set(fmt1["channel"]) == {"all"} and len(fmt1) == len(mixed.query("dataset == 'dsA'"))
    one = fmt1[(fmt1["family"] == "mlr") & (fmt1["train"] == "s3") & (fmt1["test"] == "s1")].iloc[0]
    assert (one["compensation_rate"], one["max_abs_residual_um"], one["rmse_um"]) == pytest.approx((-1.5, 25.0, 12.5))


def test_channel_table_best_and_baseline_lines(spin_report):
    out, _, _ = spin_report
    text = compact((out / "details.md").read_text(encoding="utf-8"))
    assert "### spin (2 error channels: ch1, ch2)" in text
    assert "| family | approach | ch1 | ch2 |" in text
    assert "| base (baseline) | single (mean) | 6.00 | **3.00** |" in text
    assert "| base (baseline) | global | 5.00 | 6.00 |" in text
    assert "| fam | single (mean) | 4.00 | 8.00 |" in text
    assert "| fam | global | **2.50** | 10.00 |" in text
    assert ("- **ch1**: best thermbench family vs best baseline: 2.50 µm vs 5.00 µm "
            "(fam · global vs base · global; better than the baseline).") in text
    assert ("- **ch2**: best thermbench family vs best baseline: 8.00 µm vs 3.00 µm "
            "(fam · single mean vs base · single mean; NOT better than the baseline).") in text
    # compensation rate per channel, best = highest: ch1 fam global 75 %, ch2 base single mean 70 %
    assert "| fam | global | **75.0%** | 0.0% |" in text
    assert "| base (baseline) | single (mean) | 40.0% | **70.0%** |" in text
    # before/after: the best thermbench model with curves; ch2's best (single) has none
    assert "- **ch1**: fam · global (2.50 µm) vs baseline base · global (5.00 µm)." in text
    assert ("- **ch2**: fam · global (10.00 µm) vs baseline base · global (6.00 µm); the lowest thermbench RMSE, "
            "fam · single mean (8.00 µm), has no curves") in text


def test_channel_figures_exist_are_listed_and_hold_the_right_cells(spin_report):
    out, _, captured = spin_report
    text = compact((out / "details.md").read_text(encoding="utf-8"))
    refs = _referenced_pngs(text)
    spin_figs = ["figures/rmse_bars__spin.png", "figures/rmse_matrix__spin__base.png",
                 "figures/rmse_matrix__spin__fam.png", "figures/best_curves__spin.png"]
    # dsA keeps the single-channel layout: comparison, 2 matrices, before/after
    dsa_figs = ["figures/compare__dsA.png", "figures/matrix__dsA__mlr.png", "figures/matrix__dsA__physics.png",
                "figures/curves__dsA.png"]
    assert sorted(refs) == sorted(spin_figs + dsa_figs)
    assert sorted(out / r for r in refs) == figure_paths(out)
    for p in figure_paths(out):
        assert p.read_bytes()[:8] == PNG_MAGIC, p
    assert text.index("## spin") > text.index("## dsA")
    # heatmap of fam: a panel per channel; rows a, b, global; columns a, b | tail
    panels = captured["rmse_matrix__spin__fam.png"]
    assert [ch for ch, _, _ in panels] == ["ch1", "ch2"]
    _, vals, own = panels[1]
    assert list(vals.index) == ["a", "b", "global"] and list(vals.columns) == ["a", "b", "tail"]
    assert vals.loc["a", "b"] == pytest.approx(12.0) and vals.loc["global", "tail"] == pytest.approx(10.0)
    assert own.loc["a", "a"] and not own.loc["a", "b"] and own.loc["global", "b"] and not own.loc["global", "tail"]


def test_baselines_are_marked(spin_report):
    out, mixed, _ = spin_report
    text = compact((out / "details.md").read_text(encoding="utf-8"))
    assert "#### base (baseline)" in text and "#### fam\n" in text
    assert "**Baselines**" in text
    summary = terminal_summary(mixed, reference=["base"])
    lines = summary.splitlines()
    assert "* = baseline family (for comparison, never chosen)" in lines
    assert any(line.startswith("spin ch1") and "base*" in line for line in lines)
    assert any(line.strip().startswith("fam ") for line in lines)


def test_format1_without_channel_column_is_unchanged(results, tmp_path):
    """The same results with channel "all" (as the benchmark now writes them) or without the
    column (older callers) give the same report and the same results.csv."""
    dsa = results[results["dataset"] == "dsA"]
    a = write_report(dsa, None, tmp_path / "a").parent / "details.md"
    b = write_report(dsa.assign(channel="all"), None, tmp_path / "b").parent / "details.md"
    assert a.read_text(encoding="utf-8") == b.read_text(encoding="utf-8")
    assert (tmp_path / "a" / "report.md").read_text(encoding="utf-8") == (tmp_path / "b" / "report.md").read_text(encoding="utf-8")
    assert (tmp_path / "a" / "results.csv").read_bytes() == (tmp_path / "b" / "results.csv").read_bytes()
    h = headline(dsa.assign(channel="all"))
    assert h.index.names == ["dataset", "family", "approach"]
    assert "RMSE per channel" not in a.read_text(encoding="utf-8")


def test_several_channels_need_rmse(tmp_path):
    with pytest.raises(ValueError, match=r"no column 'rmse_um'.*\['spin'\]"):
        write_report(_spin_results().drop(columns=["rmse_um"]), None, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_terminal_summary_with_channels_fits_120_columns():
    """Five channels, nine families with long names, four approaches: labels 'dataset chN',
    every line at most 120 characters."""
    rng = np.random.default_rng(1)
    states = ["rpm1250", "rpm2500", "rpm3750", "rpm5000", "rpm3500"]
    fams = ["baseline_ols", "baseline_rf", "baseline_hgb", "mlr_seed001", "mlr_seed002", "mlr_seed004", "lssvm",
            "ar_seed003", "physics_spindle"]
    rows = []
    for ch in ["ch1", "ch2", "ch3", "ch4", "ch5"]:
        for fam in fams:
            for app, trains in [("single", states), ("global", ["all"]), ("bank", ["all"]), ("bank_soft", ["all"])]:
                for tr in trains:
                    for run in states + ["tail"]:
                        rows.append({"dataset": "fl_thermal", "channel": ch, "family": fam, "approach": app,
                                     "train": tr, "run_id": run, "kind": "state" if run in states else "validation",
                                     "own": run == tr or (tr == "all" and run in states),
                                     "compensation_rate": rng.uniform(-30.0, 1.0),
                                     "max_abs_residual_um": rng.uniform(0.0, 999.0)})
    text = terminal_summary(pd.DataFrame(rows), reference=["baseline_ols", "baseline_rf", "baseline_hgb"])
    lines = text.splitlines()
    assert max(map(len, lines)) <= 120, max(lines, key=len)
    assert sum(line.startswith("fl_thermal ch3") for line in lines) >= 1
    assert "baseline_rf*" in text and "bank_soft:val" in text


def test_rmse_matrix_rows_are_the_same_in_every_channel():
    """A family whose single-state fits all failed on ch2 still gets rows a, b there (n/a)."""
    spin = _spin_results()
    spin = spin[~((spin["channel"] == "ch2") & (spin["family"] == "fam") & (spin["approach"] == "single"))]
    r = bench_results._check_results(spin)
    fam = r[(r["dataset"] == "spin") & (r["family"] == "fam")]
    models = tables._matrix_models(fam, ["a", "b"])
    assert models == [("a", "single", "a"), ("b", "single", "b"), ("global", "global", "all")]
    v1, _ = tables._test_matrix(fam[fam["channel"] == "ch1"], "rmse_um", models, ["a", "b", "tail"])
    v2, o2 = tables._test_matrix(fam[fam["channel"] == "ch2"], "rmse_um", models, ["a", "b", "tail"])
    assert list(v1.index) == list(v2.index) == ["a", "b", "global"]
    assert v1.loc["b", "tail"] == pytest.approx(5.0)
    assert np.isnan(v2.loc["a"]).all() and not o2.loc["a"].any()
    assert v2.loc["global", "tail"] == pytest.approx(10.0) and o2.loc["global", "a"]


def test_a_list_in_the_header_becomes_bullets_below_its_table():
    # a benchmark can flag hundreds of models: as one table cell, that list widened every row of
    # the header table to its length (14 000 characters in make demo's report.md)
    flags = [f"seed00{i}_x/mlr_seed001/bank_soft: worse than no compensation on run(s) ['r{i}']" for i in range(60)]
    md = markdown._meta_md({"command": "thermbench benchmark", "datasets": "a, b", "flagged (never chosen)": flags})
    lines = md.splitlines()
    table = [ln for ln in lines if ln.startswith("|")]
    assert len(table) == 5  # header, rule, three rows
    assert max(map(len, table)) < 80
    assert any("flagged (never chosen)" in ln and "60, listed below" in ln for ln in table)
    bullets = [ln[2:] for ln in lines if ln.startswith("- ")]
    assert bullets == flags
    assert lines.index("**flagged (never chosen)**") > lines.index(table[-1])


def test_the_run_keeps_short_cells_long_values_as_bullets_and_lists_in_findings_md(results, tmp_path):
    """report.md's run table holds short values only: a long value is a bullet below it, a list of
    findings (a benchmark flags dozens of models) goes to findings.md, linked from its row; a later
    report without findings takes away the findings.md the earlier one wrote."""
    flags = [f"seed00{i}_x/mlr_seed001/bank_soft: worse than no compensation on run(s) ['r{i}']" for i in range(60)]
    chosen = "; ".join(f"case{i}: family{i} (global)" for i in range(8))  # 207 characters
    meta = {"command": "thermbench benchmark", "chosen models": chosen, "flagged (never chosen)": flags}
    out = tmp_path / "out"
    md = write_report(results[results["dataset"] == "dsA"], None, out, meta=meta).read_text(encoding="utf-8")
    run = md[md.index("## The run"):].splitlines()
    table = [ln for ln in run if ln.startswith("|")]
    assert len(table) == 4 and max(map(len, table)) <= 100  # header, rule, command, flagged
    assert any("flagged (never chosen)" in ln and "60, in [findings.md](findings.md)" in ln for ln in table)
    assert f"- **chosen models**: {chosen}" in run and run.index(f"- **chosen models**: {chosen}") > run.index(table[-1])
    assert not any(f in md for f in flags)
    findings = (out / "findings.md").read_text(encoding="utf-8").splitlines()
    assert "[the report](report.md)" in findings[2] and "## flagged (never chosen) (60)" in findings
    assert [ln[2:] for ln in findings if ln.startswith("- ")] == flags
    write_report(results[results["dataset"] == "dsA"], None, out, meta={"command": "thermbench benchmark"})
    assert not (out / "findings.md").exists() and "findings.md" not in (out / "report.md").read_text(encoding="utf-8")
