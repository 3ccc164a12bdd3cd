"""Plain experiment functions (the CLI and Hydra jobs are thin layers over these).

:func:`cross_condition` fits a fresh clone of a model on some runs of a dataset and
scores it on every run: how well the model holds up in loading states it was not
trained on (seed 001 §5, seed 002 §3).
"""

from __future__ import annotations

import time
from typing import Sequence

import pandas as pd
from hydra.utils import instantiate
from omegaconf import OmegaConf
from sklearn.base import clone

from .config import config_dir
from .metrics import evaluate


def model_from_config(name_or_cfg) -> object:
    """A model from ``conf/model/<name>.yaml`` (or a config mapping with ``_target_``)."""
    if isinstance(name_or_cfg, str):
        path = config_dir() / "model" / f"{name_or_cfg}.yaml"
        if not path.exists():
            known = sorted(p.stem for p in (config_dir() / "model").glob("*.yaml"))
            raise ValueError(f"model {name_or_cfg!r}: no {path}; known models: {known}")
        name_or_cfg = OmegaConf.load(path)
    return instantiate(name_or_cfg, _convert_="all")


def cross_condition(model, dataset, train_runs: Sequence[str], eval_runs: Sequence[str] | None = None) -> pd.DataFrame:
    """Fit ``clone(model)`` on ``train_runs``; one metrics row per evaluated run,
    with ``own`` marking the training runs and ``fit_s`` the fitting time."""
    m = clone(model)
    t0 = time.perf_counter()
    m.fit(dataset, list(train_runs))
    fit_s = time.perf_counter() - t0
    res = evaluate(m, dataset, eval_runs)
    res.insert(1, "own", res["run_id"].isin(list(train_runs)))
    res["train"] = "+".join(train_runs)
    res["fit_s"] = fit_s
    return res
