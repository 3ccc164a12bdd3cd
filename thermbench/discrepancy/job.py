"""The ``thermbench diagnose`` job: the config checked key by key before anything is loaded
(a mistake is one :class:`~thermbench.discrepancy.workflow.DiagnoseError` line naming the key),
the dataset and its family loaded, the workflow (:func:`~thermbench.discrepancy.workflow.run_diagnosis`)
run, ``diagnosis.json``, ``report.md`` and the figures written atomically into the output
directory and logged to MLflow.
"""

from __future__ import annotations

import json
import os
from dataclasses import fields
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from ..data.io import Dataset, load_dataset
from ..outputs import check_output_dir, output_dir
from .search import ScrewFamily, Settings
from .significance import SignificanceTest
from .workflow import DiagnoseError, _check_effects, run_diagnosis


def physics_view(ds: Dataset) -> Dataset:
    """What the workflow confronts the screw physics model with: a format 1 dataset as it is; a
    format 2 one through its one along-axis channel, which needs a screw block. Anything else
    is one line saying what is missing (a spindle test has no screw to simulate)."""
    from ..models.base import NEEDS

    if ds.metadata.version == 1:
        return ds
    along = [c for c, m in ds.metadata.error_channels().items() if m.kind == "along_axis"]
    missing = ([NEEDS["screw"]] if ds.metadata.screw is None else []) + ([NEEDS["along_axis"]] if not along else [])
    if missing:
        raise DiagnoseError(f"{ds.path}: the discrepancy workflow confronts the screw physics model with the data; it "
                            f"needs {'; and '.join(missing)}, and this dataset (a test of: "
                            f"{', '.join(ds.metadata.parts or [])}) has none")  # fmt: skip
    if len(along) > 1:
        raise DiagnoseError(f"{ds.path}: {len(along)} along-axis channels {along}; the workflow takes one: "
                            "write a dataset with that channel only")  # fmt: skip
    return ds.channel_view(along[0])


def _number(value, key: str, kind=float, lo: float | None = None):
    """``value`` as ``kind``, finite (and >= ``lo`` when given), else a one-line error naming ``key``."""
    try:
        if isinstance(value, bool):
            raise ValueError
        out = kind(value)
    except (TypeError, ValueError, OverflowError):
        raise DiagnoseError(f"config key {key!r}: expected {'an integer' if kind is int else 'a number'}, got {value!r}") from None
    if not np.isfinite(out):
        raise DiagnoseError(f"config key {key!r}: expected a finite number, got {value!r}")
    if lo is not None and out < lo:
        raise DiagnoseError(f"config key {key!r}: expected a number >= {lo:g}, got {value!r}")
    return out


#: lowest allowed value of the numeric physics keys: (bound, strict: value > bound, else >=)
_PHYSICS_LOWEST = {"dx_m": (0, True), "dt_s": (0, True), "macro_dt_s": (0, True), "max_iter": (1, False),
                   "ftol": (0, True), "geometric_degree": (0, False)}  # fmt: skip


def _check_physics(physics: dict) -> None:
    """The identification model's numbers (``physics.*``) in range, before any data is read:
    steps and tolerances > 0, at least one iteration, ``macro_dt_s`` a whole multiple of
    ``dt_s`` (what :class:`thermbench.sim.parts.Numerics` requires)."""
    from ..sim.parts import Numerics

    for k, (lowest, strict) in _PHYSICS_LOWEST.items():
        if k in physics and (physics[k] <= lowest if strict else physics[k] < lowest):
            raise DiagnoseError(f"config key 'physics.{k}': must be {'>' if strict else '>='} {lowest}, got {physics[k]!r}")
    steps = {k: physics[k] for k in ("dx_m", "dt_s", "macro_dt_s") if k in physics}
    try:
        Numerics(**steps)
    except ValueError:
        dt_s, macro_dt_s = steps.get("dt_s", Numerics.dt_s), steps.get("macro_dt_s", Numerics.macro_dt_s)
        raise DiagnoseError(f"config key 'physics.macro_dt_s': must be a whole multiple of physics.dt_s "
                            f"(got macro_dt_s={macro_dt_s!r}, dt_s={dt_s!r})") from None  # fmt: skip


#: PhysicsModel options the diagnose config may set (the rest are the workflow's to choose)
PHYSICS_KEYS = {"dx_m": float, "dt_s": float, "macro_dt_s": float, "max_iter": int, "ftol": float,
                "geometric_degree": int, "preprocess": None, "bounds": None}  # fmt: skip


def settings_from_config(cfg, say: Callable[[str], None] = print, family=None) -> Settings:
    """:class:`Settings` from the composed ``conf/diagnose.yaml``, every key checked (the
    candidates and start grids against ``family``'s library; None: the screw's)."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    test = dict(cfg.get("test") or {})
    known = {f.name for f in fields(SignificanceTest)}
    if bad := sorted(set(test) - known):
        raise DiagnoseError(f"config key 'test': unknown key(s) {bad}; known: {sorted(known)}")
    t = SignificanceTest(**{k: _number(v, f"test.{k}") for k, v in test.items()})
    if t.within_x_floor < 1.0:
        raise DiagnoseError(f"config key 'test.within_x_floor': expected a number >= 1 (a perfect model's held-out "
                            f"RMSE is the noise floor itself), got {t.within_x_floor:g}")  # fmt: skip
    physics = dict(cfg.get("physics") or {})
    if bad := sorted(set(physics) - set(PHYSICS_KEYS)):
        raise DiagnoseError(f"config key 'physics': unknown or reserved key(s) {bad}; allowed: {sorted(PHYSICS_KEYS)}")
    physics = {k: (_number(v, f"physics.{k}", PHYSICS_KEYS[k]) if PHYSICS_KEYS[k] else v) for k, v in physics.items()}
    _check_physics(physics)
    family = family or ScrewFamily()
    own_params = family.own_params
    starts = {}
    for eid, params in dict(cfg.get("starts") or {}).items():
        searched = sorted(e for e in (*family.canonical, *family.open) if own_params(e))
        if eid not in searched or not isinstance(params, dict):
            raise DiagnoseError(f"config key 'starts.{eid}': expected one of {searched} with "
                                f"{{param: [values]}}, e.g. +starts.motor_heat.tau_s=[600,1800]")  # fmt: skip
        for param, values in params.items():
            if param not in own_params(eid):
                raise DiagnoseError(f"config key 'starts.{eid}.{param}': {eid} has {list(own_params(eid))}")
            values = values if isinstance(values, (list, tuple)) else [values]
            starts.setdefault(eid, {})[param] = [_number(v, f"starts.{eid}.{param}") for v in values]
    return Settings(
        physics=physics,
        starts=starts,
        test=t,
        candidates=_check_effects(_as_list(cfg.get("candidates")) or list(family.candidates), "candidates", open_terms=True,
                                  family=family),  # fmt: skip
        say=say,
        refit=_refit(cfg.get("refit", 3)),
        family=family,
    )


def _refit(v) -> int:
    n = _number(v, "refit", int)
    if n < 1:
        raise DiagnoseError(f"config key 'refit': expected an integer >= 1 (candidates re-identified per step), got {v!r}")
    return n


def _as_list(v) -> list[str]:
    if v is None:
        return []
    if isinstance(v, str):
        return [s for s in v.split(",") if s.strip()]
    return [str(x) for x in v]


def check_out_dir(out_dir, data_dir, force: bool = False) -> Path:
    """The output directory, refused when writing there could lose anything
    (:func:`thermbench.outputs.check_output_dir`: it is, contains or lies in a dataset, or
    holds files that an earlier diagnosis did not write), or when it is not writable."""
    out = Path(out_dir).expanduser().resolve()
    data = Path(data_dir).expanduser().resolve()
    if out == data or data.is_relative_to(out) or out.is_relative_to(data):
        raise DiagnoseError(f"--out {out}: is, contains or lies inside the dataset directory {data}; choose another directory")
    check_output_dir(out, "diagnosis", force=force)
    parent = out.parent
    while not parent.exists():
        parent = parent.parent
    if not os.access(parent, os.W_OK):
        raise DiagnoseError(f"--out {out}: {parent} is not writable")
    return out


def load_for_diagnosis(conf: dict):
    """The dataset the workflow confronts, its family and the runs held out of the search.

    ``data_dir`` is a dataset directory or a ``conf/dataset`` option (``fl_thermal``). A screw
    axis (format 1, or an along-axis channel of a dataset with a screw) is confronted with the
    seed 000 physics model as it is; a fixed-point channel (a spindle test) with the lumped
    network (:mod:`.spindle`), through its segments (each with the test's log from its start,
    ``history``) and with the option's validation runs held out (``holdout`` overrides)."""
    from ..errors import ExperimentError
    from ..bench.splits import dataset_option, dataset_view, load_source
    from .spindle import NETWORK_KEYS, spindle_family

    entry, channel = str(conf["data_dir"]), conf.get("channel")
    holdout, history = conf.get("holdout"), conf.get("history")
    if history is not None and not isinstance(history, bool):
        raise DiagnoseError(f"config key 'history': expected true or false, got {history!r}")
    if (Path(entry) / "metadata.yaml").is_file():
        ds, validation = load_dataset(entry), []
    else:
        try:
            _, dcfg = dataset_option(entry, "data_dir")
            ds = load_source(dcfg)[0]
        except ExperimentError as exc:
            raise DiagnoseError(str(exc)) from None
        validation = list(dcfg.get("validation") or [])
        history = dcfg.get("history") if history is None else history
    channels = ds.metadata.error_channels() if ds.metadata.version == 2 else {}
    if channel is not None and channel not in channels:
        raise DiagnoseError(f"config key 'channel': {channel!r} is not an error channel of {ds.path}; "
                            f"its channels: {list(channels) or 'none (a format 1 dataset has one error)'}")  # fmt: skip
    if channel is None and len(channels) > 1 and not any(m.kind == "along_axis" for m in channels.values()):
        raise DiagnoseError(f"config key 'channel': {ds.path} has {len(channels)} error channels {list(channels)}; "
                            f"name one, e.g. --channel {next(iter(channels))}")  # fmt: skip
    kind = channels[channel].kind if channel is not None else (next(iter(channels.values())).kind if len(channels) == 1 else None)
    if kind != "fixed_point":
        if holdout:
            raise DiagnoseError("config key 'holdout': runs held out of the search are for a spindle test; on a screw "
                                "axis use cv: {train: [...], test: [...]}")  # fmt: skip
        return physics_view(ds.channel_view(channel) if channel is not None else ds), ScrewFamily(), []
    view = dataset_view(ds, channel or next(iter(channels)), segments=True, history=True if history is None else history)
    holdout = validation if holdout is None else _as_list(holdout)
    if bad := [r for r in holdout if r not in view.run_ids]:
        raise DiagnoseError(f"config key 'holdout': runs {bad} are not in the dataset; its runs: {list(view.run_ids)}")
    net = dict(conf.get("spindle") or {})
    if bad := sorted(set(net) - set(NETWORK_KEYS)):
        raise DiagnoseError(f"config key 'spindle': unknown or reserved key(s) {bad}; allowed: {sorted(NETWORK_KEYS)}")
    net = {k: (_number(v, f"spindle.{k}", NETWORK_KEYS[k], lo=1 if NETWORK_KEYS[k] is int else 0) if NETWORK_KEYS[k] else v)
           for k, v in net.items()}  # fmt: skip
    try:
        family = spindle_family(view, [r for r in view.run_ids if r not in holdout], net, history=history is not False)
    except ValueError as exc:
        raise DiagnoseError(str(exc)) from None
    return view, family, holdout


def diagnose(cfg, say: Callable[[str], None] | None = None) -> dict:
    """The ``thermbench diagnose`` job: ``cfg`` is ``conf/diagnose.yaml`` composed (a
    DictConfig or a plain mapping). Reads only the files of ``cfg.data_dir``."""
    from omegaconf import DictConfig, OmegaConf

    from .. import tracking
    from .report import terminal_verdict, write_figures, write_markdown

    conf = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    say = say or (lambda m: print(m, flush=True))
    for key in ("data_dir", "out_dir"):
        if not conf.get(key) or conf[key] == "???":
            raise DiagnoseError(f"config key {key!r}: required (thermbench diagnose DATA_DIR --out OUT_DIR)")
    # everything the user can get wrong is checked before anything is loaded or fitted: the numbers
    # first, then (the dataset says which library applies) the effects or terms named
    settings_from_config({**conf, "candidates": None, "starts": None, "base": None}, say)
    max_effects = _number(conf.get("max_effects", 3), "max_effects", int)
    noise = dict(conf.get("noise") or {})
    window_s = _number(noise.get("repeat_window_s", 60.0), "noise.repeat_window_s", lo=0.0)
    min_groups = _number(noise.get("min_groups", 20), "noise.min_groups", int)
    force = conf.get("force", False)
    if not isinstance(force, bool):
        raise DiagnoseError(f"config key 'force': expected true or false, got {force!r}")
    if Path(str(conf["data_dir"])).is_dir():
        check_out_dir(conf["out_dir"], conf["data_dir"], force)
    ds, family, holdout = load_for_diagnosis(conf)
    base = _check_effects(_as_list(conf.get("base")), "base", family=family)
    settings = settings_from_config(conf, say, family)
    out = check_out_dir(conf["out_dir"], ds.path if ds.path is not None else conf["data_dir"], force)
    track = bool(conf.get("track", True))
    exp_id = tracking.connect(conf["tracking"]) if track else None  # an unreachable server fails first
    d = run_diagnosis(ds, base=base, max_effects=max_effects, cv=conf.get("cv", "loro"), settings=settings,
                      noise_window_s=window_s, noise_min_groups=min_groups, holdout=holdout)  # fmt: skip
    tables = d.pop("_tables")
    d = _finite(d)
    with output_dir(out, "diagnosis", force=force) as tmp:
        (tmp / "diagnosis.json").write_text(json.dumps(d, indent=2, allow_nan=False, default=_json_default), encoding="utf-8")
        write_figures(d, tables, tmp, settings.test.explained_x_floor)
        write_markdown(d, tmp)
        pd.concat([t.assign(model=k) for k, t in tables.items()], ignore_index=True).to_csv(tmp / "heldout_residuals.csv", index=False)
    if track:
        import mlflow

        with mlflow.start_run(experiment_id=exp_id, run_name=f"diagnose | {ds.metadata.machine.name}") as run:
            mlflow.set_tags(tracking.standard_tags(ds.content_hash(), tracking.config_hash(conf), "diagnose")
                            | {"missing_effects": ",".join(d["missing_effects"]) or "none", "verdict": d["verdict"]})  # fmt: skip
            tracking.log_config(conf)
            tracking.log_dataset(ds, ds.metadata.machine.name, "evaluation", digest=ds.content_hash())
            mlflow.log_metrics({"noise_floor_um": d["noise_floor_um"], "heldout_rmse_base_um": d["final"]["heldout_rmse_base_um"],
                                "heldout_rmse_final_um": d["final"]["heldout_rmse_um"], "n_missing": len(d["missing_effects"]),
                                "runtime_s": d["runtime_s"]})  # fmt: skip
            mlflow.log_artifacts(str(out), artifact_path="diagnosis")
        d["mlflow_run_id"] = run.info.run_id
    say(terminal_verdict(d, out))
    return d


def _finite(o):
    """NaN and infinities -> None, so that diagnosis.json is strict JSON."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    if isinstance(o, (float, np.floating)) and not np.isfinite(o):
        return None
    return o


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")
