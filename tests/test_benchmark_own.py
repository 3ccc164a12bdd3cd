"""The benchmark pointed at a user's own dataset: an entry of ``datasets`` that is a
dataset directory is that dataset, named by its machine; with ``families: null`` it gets every
family, and each it cannot serve is said in one line. Each mistake is one line naming the key."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.test_benchmark import _cfg
from tests.test_import_shapes import shape1
from thermbench import bench as bm
from thermbench.config import group_option
from thermbench.data.importer import import_dataset
from thermbench.experiment import ExperimentError, dataset_option


@pytest.fixture(scope="module")
def lathe(tmp_path_factory):
    root = tmp_path_factory.mktemp("lathe")
    mapping, _ = shape1(root / "files")
    import_dataset(mapping, root / "lathe_d")
    return root / "lathe_d"


def test_a_directory_is_a_dataset_named_by_its_machine_with_every_family(lathe, tmp_path, capsys):
    option, dcfg = dataset_option(str(lathe), "datasets")
    assert option is None and dcfg["source"]["path"] == str(lathe) and dcfg["name"] is None
    cfg = _cfg(tmp_path, f"datasets=[{lathe}]", "families=null", "bank_families=[]")
    todo = bm.tasks(cfg)
    families = {t["family"] for t in todo}
    # every model option but the bank preset (the bank approaches build banks of each family) ...
    assert "bank_mlr_seed002" not in families and {"baseline_ridge", "baseline_ols", "mlr_seed002", "lssvm"} <= families
    # ... but those that need what a spindle test on a lathe lacks: skipped, one line each
    err = capsys.readouterr().err
    for fam in ("physics", "mlr_seed001"):
        assert fam not in families and err.count(f"skipped {fam} on {lathe}") == 1
    # no operating input (the shape-1 import declares operating: []): the families driven by one
    for fam in ("ar_seed003", "physics_spindle", "physics_spindle_hybrid"):
        assert fam not in families and err.count(f"skipped {fam} on {lathe}: needs an operating input") == 1
    # no sensor at seed 004's screw locations (bearing housings, nut)
    assert "mlr_seed004" not in families
    assert err.count(f"skipped mlr_seed004 on {lathe}: needs temperature sensors at fixed_bearing_housing") == 1
    out = bm.run_task(**{**next(t for t in todo if t["family"] == "baseline_ols"), "approaches": ["global"]})
    assert out["dataset"] == "lathe_d" and set(out["results"]["run_id"]) == {"Day_1", "Day_2", "Day_3"}


@pytest.mark.parametrize("entry, message", [
    ("path", "config key 'datasets': option 'path' reads a dataset directory: give the directory itself"),
    ("fl_thermall", "config key 'datasets': 'fl_thermall' is neither a dataset option (fl_thermal, "),
    ("no/such/dir", "nor a dataset directory (no such directory; a lab's files come in with thermbench import)"),
])
def test_a_wrong_entry_is_one_line(tmp_path, entry, message):
    with pytest.raises(ExperimentError) as exc:
        bm.tasks(_cfg(tmp_path, f"datasets=[{entry}]", "families=[baseline_ols]", "bank_families=[]"))
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_dataset_source_path_on_the_benchmark_says_what_it_takes(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "thermbench.cli", "benchmark", "dataset.source.path=x"],
                          capture_output=True, text=True, cwd=tmp_path)  # fmt: skip
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "this command takes datasets=[...], each a dataset option or a dataset directory" in lines[0]
    assert "did you mean" not in lines[0]


def test_a_directory_gets_the_benchmarks_budget_for_costly_families(lathe, tmp_path):
    """conf/benchmark.yaml's benchmark_models: on a dataset directory (no option of its own to set it)
    each lssvm / gru fit of the ~90 per family takes the budget; a mistake in it names the key."""
    cfg = _cfg(tmp_path, f"datasets=[{lathe}]", "families=[lssvm,gru,mlp]", "bank_families=[]")
    by = {t["family"]: t["model_cfg"] for t in bm.tasks(cfg)}
    assert (by["lssvm"]["max_samples"], by["lssvm"]["iters"]) == (600, 20)
    assert (by["gru"]["max_samples"], by["gru"]["max_epochs"]) == (600, 300)
    assert by["mlp"] == group_option("model", "mlp")  # no budget given: the option as it is
    # a dataset option keeps its own (fl_thermal's lssvm subsample is 300)
    cfg = _cfg(tmp_path, "datasets=[fl_thermal]", "families=[lssvm]", "bank_families=[]")
    assert bm.tasks(cfg)[0]["model_cfg"]["max_samples"] == 300
    cfg = _cfg(tmp_path, f"datasets=[{lathe}]", "families=[gru]", "bank_families=[]", "+benchmark_models.gru.max_epoch=5")
    with pytest.raises(ExperimentError, match=r"^config key 'benchmark_models.gru.max_epoch': conf/model/gru.yaml has no "
                                              r"parameter 'max_epoch'"):  # fmt: skip
        bm.tasks(cfg)


@pytest.mark.parametrize("extra, message", [
    (["cv=lomo"], "config key 'cv': expected one of loro, group_kfold, declared or null, got 'lomo'"),
    (["cv=group_kfold", "cv_folds=7"], "config key 'cv_folds': expected an integer from 2 to the number of runs (3), got 7"),
])  # fmt: skip
def test_a_cv_mistake_is_one_line_before_any_fit(lathe, tmp_path, extra, message):
    cfg = _cfg(tmp_path, f"datasets=[{lathe}]", "families=[baseline_ols]", "bank_families=[]", *extra)
    with pytest.raises(ExperimentError) as err:
        bm.tasks(cfg)
    assert str(err.value) == message


def test_the_adaptive_approach_goes_through_the_report(lathe, tmp_path):  # noqa: F811
    """approaches global + adaptive on the three days: results.csv has the probe rows with their
    counts and intervals, the report is written, and the chosen model is an open-loop one."""
    import pandas as pd

    cfg = _cfg(tmp_path, f"datasets=[{lathe}]", "families=[thermal_lag,baseline_ridge]", "bank_families=[]",
               "approaches=[global,adaptive]", "probe.every_s=[600]")  # fmt: skip
    res = bm.benchmark(cfg)
    table = pd.read_csv(tmp_path / "reports" / "results.csv")
    probe = table[table["approach"].str.startswith(("adaptive-", "naive_probe-"))]
    assert set(probe["approach"]) == {"adaptive-600s", "naive_probe-600s", "adaptive-uncertainty"}
    assert (probe["probes"] >= 1).all() and not probe["own"].any()
    assert set(probe["family"]) == {"thermal_lag", "baseline_ridge"}  # the baseline's naive peer too
    glob = table[table["approach"] == "global"]
    assert set(glob["family"]) == {"thermal_lag", "baseline_ridge"}
    assert glob["coverage_90"].between(0, 1).all() and (glob["half_width_um"] > 0).all()
    assert (tmp_path / "reports" / "report.md").is_file() and res is not None
    # the report's RMSE against probes per hour: the table is the mean over the held-out runs of results.csv
    text = (tmp_path / "reports" / "details.md").read_text()  # report.md links it
    assert "## Probe readings: RMSE against probes per hour" in text
    figs = list((tmp_path / "reports" / "figures").glob("probes__*.png"))
    assert len(figs) == 1 and f"figures/{figs[0].name}" in text
    ad = probe[(probe["approach"] == "adaptive-600s") & (probe["family"] == "thermal_lag")]
    line = next(ln for ln in text.splitlines() if "| thermal_lag " in ln and "| adaptive " in ln and "| 600s " in ln)
    assert f"{ad['rmse_um'].mean():.2f}" in line and f"{ad['probes_per_h'].mean():.2f}" in line


def test_every_fold_fit_is_scored_as_deployed_beside_itself(lathe, tmp_path):  # noqa: F811
    """approach global on the three days: each fold's thermal_lag fit is also scored as the compensator
    runs it (rows as_deployed: never a baseline's), and where no sensor was judged faulty and no bound
    acted, its score is the raw fit's to the digit; the answer says both."""
    import pandas as pd

    cfg = _cfg(tmp_path, f"datasets=[{lathe}]", "families=[thermal_lag,baseline_ridge]", "bank_families=[]",
               "approaches=[global]")  # fmt: skip
    bm.benchmark(cfg)
    table = pd.read_csv(tmp_path / "reports" / "results.csv", keep_default_na=False, na_values=[""])
    dep = table[table["approach"] == "as_deployed"]
    glob = table[(table["approach"] == "global") & (table["kind"] == "validation")]
    assert set(dep["family"]) == {"thermal_lag"} and not dep["chosen"].any()
    both = dep.merge(glob[glob["family"] == "thermal_lag"], on=["fold", "test"], suffixes=("", "_raw"))
    assert len(both) == len(dep) == glob["family"].eq("thermal_lag").sum()
    quiet = both[both["faults"].isna() & (both["bounded_share"] == 0)]
    assert len(quiet) > 0
    assert (quiet["rmse_um"] == quiet["rmse_um_raw"]).all()
    report = (tmp_path / "reports" / "report.md").read_text()
    assert "as deployed µm" in report.splitlines()[2]


def test_the_models_of_a_benchmark_on_a_directory_export_without_naming_the_dataset_again(lathe, tmp_path):
    """The benchmark's manifest records where a dataset directory was (``dataset_path``), so
    ``thermbench export`` of its models replays the held-out runs from it with no export.dataset;
    a manifest whose directory is gone is one line saying to set export.dataset."""
    import yaml

    from thermbench.config import ConfigError
    from thermbench.data.io import load_dataset
    from thermbench.export.job import run_export

    cfg = _cfg(tmp_path, f"datasets=[{lathe}]", "families=[ridge_history,baseline_ridge]", "bank_families=[]",
               "approaches=[global]")  # fmt: skip
    bm.benchmark(cfg)
    models = tmp_path / "models"
    man = yaml.safe_load((models / "manifest.yaml").read_text())
    key = next(k for k in man if "__ridge_history__" in k)
    lathe_ds = load_dataset(lathe)
    assert man[key]["dataset_path"] == str(lathe.resolve())
    from thermbench.config import load_config

    def export_cfg(out, *extra):  # a tracking store of its own: what the export knows of the dataset is the manifest's
        return load_config("export", [f"export.source={models}", f"export.select=[{key}]", f"export.out_dir={out}",
                                      "export.n_jobs=1", "export.onnx=false", f"tracking.uri=sqlite:///{tmp_path}/other.db",
                                      f"tracking.artifact_root={tmp_path}/other_art", *extra])  # fmt: skip

    # the lathe logs every 120 s, the C runtime takes a sample at least every 60 s: the parity replay of the
    # lathe's runs (found from the manifest) fills the log in as the compensator samples, both sides alike
    import json

    rows, _ = run_export(export_cfg(tmp_path / "x"))
    assert list(rows["model"]) == [key] and (tmp_path / "x" / key / "model.tbm").is_file()
    parity = json.loads((tmp_path / "x" / key / "manifest.json").read_text())["parity"]
    assert parity["model"]["max_abs_diff_um"] < 1e-9 and parity["model"]["float_max_abs_diff_um"] < 0.01
    assert parity["log"].startswith("the runs' logs are up to 120 s apart, over the C runtime's 60 s")
    assert parity["model"]["n_samples"] > 2 * sum(len(lathe_ds.process_run(r)) for r in parity["runs"]) - 10
    man[key]["dataset_path"] = str(tmp_path / "gone")
    (models / "manifest.yaml").write_text(yaml.safe_dump(man, sort_keys=False))
    with pytest.raises(ConfigError, match=r"is not a dataset directory here; set export.dataset"):
        run_export(export_cfg(tmp_path / "y"))
    for v in man.values():  # a directory with no model marked chosen, asked for the chosen one: says so
        v["chosen"] = False
    (models / "manifest.yaml").write_text(yaml.safe_dump(man, sort_keys=False))
    chosen = load_config("export", [f"export.source={models}", "export.select=chosen", f"export.out_dir={tmp_path / 'z'}"])
    with pytest.raises(ConfigError, match=r"^config key 'export.select': chosen, but .*manifest.yaml marks no model "
                                          r"chosen \(chosen: true\); name the models instead, e.g. export.select=\["):
        run_export(chosen)


def test_the_single_matrix_is_skipped_above_single_max_runs_and_said(lathe, tmp_path, capsys):
    """3 runs: with single_max_runs 2 the single approach (3 fits scored on 3 runs each) is not run, in one
    line; with 3 it is, each run's fit scored on all 3 runs."""
    base = [f"datasets=[{lathe}]", "families=[baseline_ols]", "bank_families=[]", "cv=loro"]
    todo = bm.tasks(_cfg(tmp_path, *base, "single_max_runs=2"))
    assert "single" not in todo[0]["approaches"] and "global" in todo[0]["approaches"]
    err = capsys.readouterr().err
    assert err.count(f"skipped single on {lathe}: 3 runs, above single_max_runs (2)") == 1
    todo = bm.tasks(_cfg(tmp_path, *base, "single_max_runs=3"))
    assert "single" in todo[0]["approaches"] and "skipped single" not in capsys.readouterr().err
    res = bm.run_task(**{**todo[0], "approaches": ["single"]})["results"]
    assert len(res) == 9 and sorted(set(res["train"])) == ["Day_1", "Day_2", "Day_3"]
    with pytest.raises(ExperimentError, match="config key 'single_max_runs': expected an integer >= 1 or null, got 0"):
        bm.tasks(_cfg(tmp_path, *base, "single_max_runs=0"))
