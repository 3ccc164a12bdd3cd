"""What a benchmark runs: its settings checked (approaches, families per dataset, intervals, outputs), and
the tasks, one per (dataset, channel, family), each with its model configuration and folds.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from omegaconf import DictConfig, OmegaConf

from .. import tracking
from ..config import group_option
from ..errors import ExperimentError
from ..experiment import plain
from ..models.base import ModelError
from .adapt import ProbePlan
from .parallel import hydra_runtime
from .splits import dataset_option, load_source, load_split, outer_folds


#: the fold name of the deployed model's choice: the inner folds over every run it is fitted on
DEPLOY_FOLD = "all runs"


#: what a cell (a family on a dataset: an approach, a fold) may fail with on its data: thermbench's own
#: ModelError, and scikit-learn's and numpy's refusals of the numbers they were given (no input left after a
#: selection, a singular matrix, non-finite values). Each is one line and a row of kind ``failed`` in
#: results.csv; the cell is no candidate of that fold and the benchmark goes on.
CELL_FAILURES = (ModelError, ValueError, np.linalg.LinAlgError, FloatingPointError)


def interval_settings(interval: Mapping | None) -> tuple[float, float]:
    """(level, kappa) of config key ``interval``, checked."""
    cfg = dict(interval or {})
    unknown = sorted(set(cfg) - {"level", "kappa"})
    if unknown:
        raise ExperimentError(f"config key(s) {['interval.' + k for k in unknown]}: unknown; known: interval.level, interval.kappa")
    level, kappa = cfg.get("level", 0.9), cfg.get("kappa", 1.0)
    if isinstance(level, bool) or not isinstance(level, (int, float)) or not 0 < level < 1:
        raise ExperimentError(f"config key 'interval.level': expected a number between 0 and 1 (0.9: a 90 % interval), got {level!r}")
    if isinstance(kappa, bool) or not isinstance(kappa, (int, float)) or not (kappa >= 0 and np.isfinite(kappa)):
        raise ExperimentError(f"config key 'interval.kappa': expected a number >= 0, got {kappa!r}")
    return float(level), float(kappa)


#: the bank approaches: name -> how the members are combined (ConditionBank ``blend``)
BANKS = {"bank": "hard", "bank_soft": "soft"}


APPROACHES = ("single", "global", *BANKS, "adaptive")


def families_by_dataset(cfg, datasets: Sequence[str]) -> dict[str, list[str]]:
    """The families to run per dataset: ``cfg.families`` for every dataset, or when it is null
    each dataset option's own ``benchmark_families`` (the shipped benchmark: the measured
    spindle test gets families the simulated axes do not)."""
    if cfg.get("families") is not None:
        fams = _names(cfg, "families", _options("model"))
        return {d: fams for d in datasets}
    out = {}
    for d in datasets:
        option, dcfg = dataset_option(d, "datasets")
        own = dcfg.get("benchmark_families")
        if own is None and option is not None and option != "path":
            raise ExperimentError(f"config key 'families': null, and conf/dataset/{d}.yaml has no benchmark_families; "
                                  f"give the families, e.g. families=[mlr_seed002]")  # fmt: skip
        if own is None:  # a dataset directory: every family (tasks() skips, in one line each, those it cannot serve)
            own = [f for f in _options("model") if not _is_bank_option(f)]
        out[d] = _names({"benchmark_families": own}, "benchmark_families", _options("model"))
    return out


def _is_bank_option(family: str) -> bool:
    """A model option that is a bank of another family (``bank_mlr_seed002``): the benchmark's
    ``bank`` approaches build banks of every family, so it is not a family of its own there."""
    return str(group_option("model", family).get("_target_", "")).endswith("ConditionBank")


def channels_of(ds, dcfg: Mapping) -> list[str]:
    """The error channels a benchmark scores ``ds`` on: the option's ``channel`` when it names
    one, every channel of a format 2 dataset when it is null, ``all`` for format 1."""
    if ds.metadata.version == 1:
        return ["all"]
    if dcfg.get("channel") is not None:
        return [str(dcfg["channel"])]
    return sorted(ds.metadata.error_channels())


def case_label(dataset: str, channel: str) -> str:
    """How a (dataset, channel) pair is named in model keys, registry names and the report:
    the dataset's name, with ``-<channel>`` for one channel of a format 2 dataset."""
    return str(dataset) if channel == "all" else f"{dataset}-{channel}"


def tasks(cfg: DictConfig, skipped: list[str] | None = None) -> list[dict]:
    """One task per (dataset, channel, family) of ``cfg.datasets`` x their error channels x ``cfg.families``.

    Each dataset is loaded (built on first use) here, once, before any task runs, so
    parallel workers never build the same dataset at the same time; its content hash
    and the code version join the task's cache key. What a dataset cannot serve (a family
    whose needs it lacks, the bank approaches when it has nothing to classify) is said in one
    line each on stderr, and appended to ``skipped``."""
    from ..models.bank import condition_inputs

    def skip(line: str) -> None:
        print(f"[benchmark] skipped {line}", file=sys.stderr, flush=True)
        if skipped is not None:
            skipped.append(line)

    interval_settings(plain_value(cfg.get("interval")))  # one line before any worker starts
    approaches = _names(cfg, "approaches", list(APPROACHES))
    if "adaptive" in approaches:
        ProbePlan.from_config(plain_value(cfg.get("probe")))
        if "global" not in approaches:
            raise ExperimentError("config key 'approaches': adaptive replays the global fits with probes; add global")
    if not approaches:
        raise ExperimentError(f"config key 'approaches': empty; choose among {', '.join(APPROACHES)}")
    datasets = _dataset_entries(cfg)
    per_dataset = families_by_dataset(cfg, datasets)
    families = list(dict.fromkeys(f for fams in per_dataset.values() for f in fams))
    # with each dataset's own families (families: null), bank families a dataset does not run are ignored there
    bank_families = _names(cfg, "bank_families", families if cfg.get("families") is not None else _options("model"),
                           required=False)  # fmt: skip
    for key, lo in (("seed", 0), ("n_jobs", -1)):
        v = cfg.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < lo or (key == "n_jobs" and v == 0):
            raise ExperimentError(f"config key '{key}': expected an integer >= {lo}{' other than 0' if key == 'n_jobs' else ''}"
                                  f", got {v!r}")  # fmt: skip
    stray = sorted(set(bank_families) - set(families))
    if stray and cfg.get("families") is not None:
        raise ExperimentError(f"config key 'bank_families': {stray} are not in 'families' {families}")
    max_runs = cfg.get("single_max_runs", None)
    if max_runs is None:
        max_runs = float("inf")
    elif isinstance(max_runs, bool) or not isinstance(max_runs, int) or max_runs < 1:
        raise ExperimentError(f"config key 'single_max_runs': expected an integer >= 1 or null, got {max_runs!r}")
    classifier = OmegaConf.to_container(cfg.classifier, resolve=True) if cfg.get("classifier") else None
    version = tracking.code_version()
    out = []
    for dname in datasets:
        option, dcfg = dataset_option(dname, "datasets")
        if option is None:  # a dataset directory: the benchmark's own settings of the costly families
            dcfg = {**dcfg, "benchmark_models": plain_value(cfg.get("benchmark_models"))}
        raw = load_source(dcfg)[0]
        for channel in channels_of(raw, dcfg):
            ccfg = dcfg if channel == "all" else {**dcfg, "channel": channel}
            split = load_split(ccfg)
            ccfg = {**ccfg, "name": split.name}  # a dataset directory: named by its machine
            ds, first = split.dataset, channel == channels_of(raw, dcfg)[0]
            data_hash = ds.content_hash()
            cv_kind, cv_folds, _ = outer_folds(split, _cv(cfg), cfg.get("cv_folds", 5))  # checked here, in one line
            n_runs = len({r for f in cv_folds for r in f.held_out})
            kept = approaches
            if "single" in approaches and cv_kind != "declared" and n_runs > max_runs:
                kept = [a for a in approaches if a != "single"]  # N fits scored on N runs each: N^2 scores
                if first:
                    skip(f"single on {dname}: {n_runs} runs, above single_max_runs ({max_runs}): the train-run x "
                         f"test-run matrix would be {n_runs} fits scored on {n_runs} runs each; raise single_max_runs "
                         "to have it")  # fmt: skip
            banked = [a for a in approaches if a in BANKS]
            try:
                if banked:
                    condition_inputs(ds, list(ds.run_ids), require=False)
            except ModelError as exc:  # e.g. runs without conditions and no operating input: nothing to classify
                if first:
                    skip(f"{', '.join(banked)} on {dname}: {exc}")
                banked = []
            for fam in per_dataset[str(dname)]:
                lacks = family_lacks(fam, ds)
                if lacks:  # e.g. the screw physics model on a spindle test: skipped there, and said so
                    if first:
                        skip(f"{fam} on {dname}: {lacks}")
                    continue
                out.append(
                    dict(
                        dataset_cfg=ccfg,
                        family=fam,
                        model_cfg=model_config(fam, dcfg, str(dname) if option else None),
                        approaches=[a for a in kept if a not in BANKS or (fam in bank_families and a in banked)],
                        classifier_cfg=classifier,
                        seed=int(cfg.seed),
                        dataset_hash=data_hash,
                        code_version=version,
                        verbose=bool(cfg.get("progress", True)),
                        channel=channel,
                        cv=_cv(cfg),
                        cv_folds=cfg.get("cv_folds", 5),
                        interval=plain_value(cfg.get("interval")),
                        probe=plain_value(cfg.get("probe")),
                    )
                )
    return out


def _dataset_entries(cfg) -> list[str]:
    """``cfg.datasets``: dataset options by name or dataset directories (each checked here, one line)."""
    value = cfg.get("datasets")
    if isinstance(value, str) or not OmegaConf.is_list(value) and not isinstance(value, (list, tuple)):
        raise ExperimentError(f"config key 'datasets': expected a list, e.g. datasets=[{value}], got {value!r}")
    if not value:
        raise ExperimentError("config key 'datasets': empty; give dataset options or directories, e.g. datasets=[fl_thermal]")
    entries = [str(v) for v in value]
    for e in entries:
        dataset_option(e, "datasets")
    return entries


def model_config(family: str, dcfg: Mapping, dname: str | None) -> dict:
    """The model option ``family`` with the settings the benchmark gives it on this dataset
    (``benchmark_models.<family>``: in ``conf/dataset/<dname>.yaml`` for a dataset option, e.g.
    fewer epochs or a smaller LSSVM subsample on a 46 h log; the benchmark's own key for a
    dataset directory, ``dname`` None). An unknown family or parameter names the key."""
    import difflib

    where = f"conf/dataset/{dname}.yaml: key 'benchmark_models" if dname else "config key 'benchmark_models"
    base = dict(group_option("model", family))
    extra = dcfg.get("benchmark_models") or {}
    if not isinstance(extra, Mapping):
        raise ExperimentError(f"{where}': expected a mapping family -> settings, got {extra!r}")
    known = _options("model")
    for fam in extra:
        if fam not in known:
            near = difflib.get_close_matches(str(fam), known, n=1)
            raise ExperimentError(f"{where}.{fam}': no model option {fam!r}{f'; did you mean {near[0]!r}?' if near else ''}")
    settings = extra.get(family) or {}
    if not isinstance(settings, Mapping):
        raise ExperimentError(f"{where}.{family}': expected a mapping parameter -> value, got {settings!r}")
    for k, v in dict(settings).items():
        if k not in base:
            raise ExperimentError(f"{where}.{family}.{k}': conf/model/{family}.yaml has no parameter {k!r}; "
                                  f"it has {sorted(base)}")  # fmt: skip
        base[k] = OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v
    return base


def plain_value(value):
    """A config node as plain data (a container resolved), anything else as it is."""
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def family_class(family: str):
    """The model class of option ``family`` (``conf/model/<family>.yaml``); for a bank option,
    the class of the models inside it. None when the option names no ``_target_``. A family
    whose optional dependency is missing raises :class:`~thermbench.errors.MissingExtra`."""
    from hydra._internal.utils import _locate

    from ..errors import MissingExtra

    opt = group_option("model", family)
    target = opt.get("_target_")
    if target is None:
        return None
    if str(target).endswith("ConditionBank") and opt.get("model", {}).get("_target_"):
        target = opt["model"]["_target_"]
    try:
        return _locate(str(target))
    except ImportError as exc:  # Hydra wraps the module's own error
        if isinstance(exc.__cause__, MissingExtra):
            raise exc.__cause__ from None
        raise


def family_lacks(family: str, ds) -> str | None:
    """What dataset ``ds`` lacks that model family ``family`` needs (its class's ``needs``,
    :func:`thermbench.models.base.missing_needs`), as text; None when it has everything."""
    from ..errors import MissingExtra
    from ..models.base import missing_needs, needs_text

    try:
        cls = family_class(family)
    except MissingExtra as exc:  # e.g. gru on the core install: the other families still run
        return str(exc)
    params = dict(group_option("model", family))
    if str(params.get("_target_", "")).endswith("ConditionBank"):  # a bank option: its members' parameters
        params = dict(params.get("model") or {})
    missing = missing_needs(cls, ds, params) if cls is not None else []
    return "needs " + needs_text(cls, missing) if missing else None


def reference_only_model(model) -> bool:
    """True for a baseline model (``reference_only`` on its class, or on a bank's members)."""
    inner = getattr(model, "model", None)
    return bool(getattr(model, "reference_only", False) or getattr(inner, "reference_only", False))


def reference_only(family: str) -> bool:
    """True for a baseline family (``reference_only`` on its class): in the tables for
    comparison, never chosen for deployment."""
    from ..errors import MissingExtra

    try:
        return bool(getattr(family_class(family), "reference_only", False))
    except MissingExtra:  # not installed, so not in the results: not a baseline either
        return False


def _options(group: str) -> list[str]:
    from ..config import config_dir

    return sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))


def _names(cfg, key: str, known: Sequence[str], required: bool = True) -> list[str]:
    """``cfg[key]`` as a list of names, each one of ``known`` (a mistake names the key, with a did-you-mean)."""
    import difflib

    value = cfg.get(key)
    if value is None and not required:
        return []
    if isinstance(value, str) or not OmegaConf.is_list(value) and not isinstance(value, (list, tuple)):
        raise ExperimentError(f"config key '{key}': expected a list, e.g. {key}=[{value}], got {value!r}")
    names = [str(v) for v in value]
    for n in names:
        if n not in known:
            close = difflib.get_close_matches(n, known, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ExperimentError(f"config key '{key}': unknown {n!r}; {hint}known: {', '.join(known)}")
    return names


def _cv(cfg) -> str | None:
    """The config's ``cv`` (null: :func:`thermbench.bench.splits.resolve_cv` decides per dataset)."""
    return None if cfg.get("cv") is None else str(cfg.get("cv"))


def _overrides() -> list[str]:
    hc = hydra_runtime()
    return list(hc.overrides.task) if hc is not None else []


#: the keys that do not change what a benchmark computes (left out of its name)
_NOT_SETTINGS = (*tracking.NON_RESULT_KEYS, "name", "force")


def output_name(cfg: DictConfig | Mapping) -> str:
    """The name of a benchmark's output set: ``cfg.name`` when given, else ``benchmark`` for
    the settings of ``conf/benchmark.yaml`` as shipped and ``benchmark-<hash>`` of the settings
    for any other (so a benchmark with other settings never replaces the demo's outputs)."""
    from ..config import ConfigError, load_config

    if cfg.get("name"):
        name = str(cfg.get("name"))
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}", name):
            raise ConfigError(f"config key 'name': {name!r} is not a usable directory name "
                              "(letters, digits, '_', '.', '-'; at most 64)")  # fmt: skip
        return name

    def settings(c) -> str:
        return tracking.config_hash({k: v for k, v in plain(c).items() if k not in _NOT_SETTINGS})

    mine = settings(cfg)
    return "benchmark" if mine == settings(load_config("benchmark")) else f"benchmark-{mine[:8]}"


def output_dirs(cfg: DictConfig | Mapping) -> tuple[Path, Path]:
    """The report and model directories of a benchmark: ``report_dir`` / ``export_dir`` when
    set, else ``reports/<name>`` and ``models/<name>`` (:func:`output_name`)."""
    name = None if cfg.get("report_dir") and cfg.get("export_dir") else output_name(cfg)
    report = Path(str(cfg.get("report_dir") or f"reports/{name}"))
    models = Path(str(cfg.get("export_dir") or f"models/{name}"))
    return report, models