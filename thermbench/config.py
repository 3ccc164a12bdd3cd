"""Locate ``conf/`` and compose Hydra configs (no hand-rolled config parsing).

:func:`load_config` composes a config; :func:`compose_checked` is what the command line
uses: it also checks the user's overrides before any work starts and turns every mistake
into one :class:`ConfigError` line with a did-you-mean (unknown key or group option,
malformed override, empty value, value of the wrong type, a mandatory ``???`` value left
out), for one job or for every job of a ``-m`` sweep.
"""

from __future__ import annotations

import copy
import difflib
import os
import re
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, ListConfig, OmegaConf

from ._resources import project_dir
from .errors import ExperimentError, UserError, one_line


class ConfigError(UserError):
    """A config or override is wrong; the message names the key."""


def config_dir() -> Path:
    """``$THERMBENCH_CONFIG_DIR``, else the ``conf/`` the package carries (a wheel), else the one at the
    top of a source checkout (thermbench/_resources.py)."""
    cand, tried = project_dir("conf", "THERMBENCH_CONFIG_DIR", "simulate.yaml")
    if not (cand / "simulate.yaml").exists():
        where = " nor ".join(str(t) for t in tried)
        raise ConfigError(f"no thermbench configuration: {where} has no simulate.yaml; set THERMBENCH_CONFIG_DIR "
                          "to a copy of the project's conf/")
    return cand


@contextmanager
def _hydra() -> Iterator[None]:
    """Hydra initialised on ``conf/`` for the duration (a running Hydra instance is cleared first)."""
    if GlobalHydra.instance().is_initialized():
        GlobalHydra.instance().clear()
    with initialize_config_dir(version_base="1.3", config_dir=str(config_dir())):
        yield


def load_config(name: str = "simulate", overrides: Sequence[str] = (), return_hydra_config: bool = False) -> DictConfig:
    """Compose ``conf/<name>.yaml`` with Hydra overrides (``key=value``, ``group=option``).

    ``return_hydra_config=True`` keeps the ``hydra`` node (its ``runtime.choices`` name
    the options picked for each group), as a ``hydra.main`` job sees it. A mistake raises
    a one-line :class:`ConfigError` (with a did-you-mean where one fits)."""
    overrides = [str(o) for o in overrides]
    with _hydra():
        try:
            return compose(config_name=name, overrides=overrides, return_hydra_config=return_hydra_config)
        except ConfigError:
            raise
        except Exception as exc:  # hydra's override/composition errors are user mistakes
            raise ConfigError(_Composer(name).explain(exc, overrides)) from None


def _has_submitit() -> bool:
    """Whether Hydra's submitit launcher plugin (the ``cluster`` extra) is installed."""
    import importlib.util

    try:
        return importlib.util.find_spec("hydra_plugins.hydra_submitit_launcher") is not None
    except ModuleNotFoundError:
        return False


def compose_checked(
    name: str,
    overrides: Sequence[str] = (),
    *,
    multirun: bool | None = None,
    fill: Mapping[str, Any] | None = None,
    require_values: bool = True,
) -> DictConfig:
    """``conf/<name>.yaml`` composed with the command line's overrides, every mistake found
    before any work starts; returns the (first) job's config without the ``hydra`` node.

    Checked, each as one :class:`ConfigError` line: malformed overrides, an empty value
    (``train=``), unknown keys and group options (with a did-you-mean), values whose type
    differs from the config's (``seed=abc``), ``???`` values left out (unless
    ``require_values=False``), interpolations of missing keys. ``fill`` sets keys the
    command fills in itself (paths from its own arguments) before the ``???`` check.

    ``multirun``: None for a command that runs one config (a sweep override is then an
    error); False for a Hydra job without ``-m`` (a sweep override asks for ``-m`` unless
    the config is a multirun by itself, e.g. ``sweep=...``); True with ``-m``: every job of
    the sweep (its command-line sweeps x ``hydra.sweeper.params``, as Hydra's basic sweeper
    expands them) is checked, and a mistake names the job's overrides.
    """
    with _hydra():
        parsed = _parse(overrides, GlobalHydra.instance().config_loader())  # the loader: for glob() sweeps
        for o in parsed:
            if o.is_sweep_override():
                line = o.input_line
                if multirun is None:
                    raise ConfigError(
                        f"override {line!r} lists several values, but this command runs one configuration; "
                        f"a list is written {o.get_key_element()}=[...], a string with commas is quoted"
                    )
                if o.is_hydra_override():
                    raise ConfigError(f"override {line!r}: a sweep over Hydra's own settings is not supported")
        composer = _Composer(name)
        hydra_ovs = [o.input_line for o in parsed if o.is_hydra_override()]
        task = [o for o in parsed if not o.is_hydra_override()]
        sweeps = [o for o in task if o.is_sweep_override()]
        if sweeps and not multirun:  # fine only in a config that is a multirun by itself (sweep=...)
            fixed = [o.input_line for o in task if not o.is_sweep_override()]
            _, base = composer.job(hydra_ovs, fixed, fill=None, require_values=False)
            if str(OmegaConf.select(base, "hydra.mode", default="")) != "RunMode.MULTIRUN":
                key = sweeps[0].get_key_element()
                raise ConfigError(
                    f"override {sweeps[0].input_line!r} lists several values: add -m to run one job per value "
                    f"(a sweep), or write a list as {key}=[...]"
                )
        # the first job: each sweep at its first value (an interval() is a sweeper plugin's to sample)
        first = []
        for o in task:
            if not o.is_sweep_override():
                first.append(o.input_line)
            elif o.is_discrete_sweep():
                values = list(o.sweep_string_iterator())
                if not values:
                    raise ConfigError(f"override {o.input_line!r} gives no value to sweep over")
                first.append(f"{o.get_key_element()}={values[0]}")
        cfg0, base = composer.job(hydra_ovs, first, fill=fill, require_values=require_values)
        if multirun or str(OmegaConf.select(base, "hydra.mode", default="")) == "RunMode.MULTIRUN":
            jobs = _sweep_jobs(base, [o.input_line for o in task])
            if jobs is not None and len(jobs) > 1:
                for job in _covering(jobs):
                    try:
                        composer.job(hydra_ovs, job, fill=fill, require_values=require_values)
                    except ConfigError as exc:
                        raise ConfigError(f"sweep job ({' '.join(job)}): {exc}") from None
        return cfg0


def with_defaults(name: str, cfg) -> dict:
    """``cfg`` (a mapping, e.g. from a test or a notebook) over the defaults of
    ``conf/<name>.yaml``, as a plain dict; a key the config does not have is an error."""
    from omegaconf.errors import OmegaConfBaseException

    base = load_config(name)
    plain = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg or {})
    try:
        merged = OmegaConf.merge(base, OmegaConf.create(plain))
        return OmegaConf.to_container(merged, resolve=True)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None)
        raise ConfigError(f"config {name!r}: key {key!r}: {str(exc).splitlines()[0]}") from None


# ------------------------------------------------------------ the checks ---
_GRAMMAR = "https://hydra.cc/docs/advanced/override_grammar/basic/"


def _parse(overrides: Sequence[str], config_loader=None) -> list:
    """Hydra's parse of each override; a malformed or empty one is a :class:`ConfigError`."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    parser = OverridesParser.create(config_loader=config_loader)
    out = []
    for text in overrides:
        text = str(text)
        try:
            (o,) = parser.parse_overrides([text])
        except OverrideParseException as exc:
            if "=" not in text and not text.startswith("~"):
                raise ConfigError(f"override {text!r} has no '=': write key=value, e.g. seed=1 or model=lssvm") from None
            why = "; ".join(ln.strip() for ln in exc.message.splitlines()
                            if ln.strip() not in ("", "^") and not ln.startswith(("See ", "Error parsing")))  # fmt: skip
            if why.startswith("LexerNoViableAltException"):
                key = text.split("=", 1)[0]
                why = f"a character in the value needs quotes, e.g. {key}='...'"
            raise ConfigError(f"malformed override {text!r}: {why or 'cannot be parsed'} (the grammar: {_GRAMMAR})") from None
        if text.endswith("=") and not o.is_delete() and o.value() == "":
            key = o.get_key_element()
            raise ConfigError(f"override {text!r} gives no value: write {key}=VALUE, or {key}=null for none")
        out.append(o)
    return out


def _sweep_jobs(cfg: DictConfig, task: list[str]) -> list[list[str]] | None:
    """The overrides of each job of a basic-sweeper multirun (None: another sweeper)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    target = str(OmegaConf.select(cfg, "hydra.sweeper._target_", default=""))
    if not target.endswith("BasicSweeper"):
        return None
    node = OmegaConf.select(cfg, "hydra.sweeper.params", default=None)
    params = OmegaConf.to_container(node, resolve=False) if node else {}
    parser = OverridesParser.create(config_loader=GlobalHydra.instance().config_loader())
    try:
        parsed = parser.parse_overrides([f"{k}={v}" for k, v in params.items()] + list(task))
        return BasicSweeper.split_arguments(parsed, None)[0]
    except Exception:  # a sweep the basic sweeper cannot expand: Hydra reports it
        return None


def _covering(jobs: list[list[str]], limit: int = 64) -> list[list[str]]:
    """All jobs of a small sweep; of a large one, a subset in which every override occurs."""
    if len(jobs) <= limit:
        return jobs
    seen: set[str] = set()
    out = []
    for job in jobs:
        if not set(job) <= seen:
            out.append(job)
            seen.update(job)
    return out


@contextmanager
def _open(cfg: DictConfig) -> Iterator[None]:
    struct = OmegaConf.is_struct(cfg)
    OmegaConf.set_struct(cfg, False)
    try:
        yield
    finally:
        OmegaConf.set_struct(cfg, struct)


def _node(cfg, key: str):
    """The node at dotted ``key`` without resolving interpolations (None when absent)."""
    node = cfg
    for seg in key.split("."):
        if not isinstance(node, DictConfig) or seg not in node.keys():
            return None
        node = node._get_node(seg)
    return node


def _flat_keys(cfg, prefix: str = "") -> list[str]:
    out = []
    if isinstance(cfg, DictConfig):
        for k in cfg.keys():
            full = f"{prefix}{k}"
            out.append(full)
            out.extend(_flat_keys(cfg._get_node(k), f"{full}."))
    return out


def _did_you_mean(word: str, known: Sequence[str]) -> str | None:
    known = [str(k) for k in known]
    lower = {k.lower(): k for k in known}
    if word.lower() in lower:
        return lower[word.lower()]
    close = difflib.get_close_matches(word, known, n=1, cutoff=0.6)
    return close[0] if close else None


def _listing(items: Sequence[str], limit: int = 20) -> str:
    items = [str(i) for i in items]
    return ", ".join(items[:limit]) + (f", ... ({len(items)} in all)" if len(items) > limit else "")


_TYPES = {bool: "true or false", int: "an integer", float: "a number"}


def _type_mistake(key: str, declared: Any, value: Any) -> str | None:
    """Why ``value`` cannot replace the config's ``declared`` value (None: it can)."""
    if value is None or isinstance(value, str) and "${" in value:
        return None
    if isinstance(declared, bool):
        ok = isinstance(value, bool)
    elif isinstance(declared, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(declared, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    else:
        return None
    if ok:
        return None
    return f"config key '{key}': expected {_TYPES[type(declared)]} (the config has {declared!r}), got {value!r}"


def _missing(cfg, prefix: str = "") -> list[str]:
    """Keys whose value is ``???`` (mandatory, not given)."""
    out = []
    if isinstance(cfg, DictConfig):
        items = [(k, cfg._get_node(k)) for k in cfg.keys()]
    elif isinstance(cfg, ListConfig):
        items = [(i, cfg._get_node(i)) for i in range(len(cfg))]
    else:
        return out
    for k, child in items:
        full = f"{prefix}{k}"
        if full == "hydra":
            continue
        if isinstance(child, (DictConfig, ListConfig)):
            if child._is_missing():
                out.append(full)
            else:
                out.extend(_missing(child, f"{full}."))
        elif child is not None and child._is_missing():
            out.append(full)
    return out


class _Composer:
    """Compositions of ``conf/<name>.yaml`` inside one Hydra initialisation, and the
    one-line explanation of Hydra's composition errors."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._groups: dict[tuple[str, ...], tuple[DictConfig, DictConfig]] = {}

    # ---------------------------------------------------------- compose ---
    def _compose(self, overrides: list[str]) -> DictConfig:
        try:
            return compose(config_name=self.name, overrides=overrides, return_hydra_config=True)
        except ConfigError:
            raise
        except Exception as exc:
            raise ConfigError(self.explain(exc, overrides)) from None

    def _is_group(self, o) -> bool:
        """As Hydra's defaults list decides: a group override, else a value override."""
        repo = GlobalHydra.instance().config_loader().repository
        return repo.group_exists(o.key_or_group) and not isinstance(o.value(), dict)

    def job(self, hydra_ovs: list[str], job: list[str], fill: Mapping[str, Any] | None,
            require_values: bool) -> tuple[DictConfig, DictConfig]:
        """One job's config (without the ``hydra`` node), checked, and the composition of its
        group options (with the ``hydra`` node: its mode, sweeper, choices)."""
        from hydra._internal.config_loader_impl import ConfigLoaderImpl

        parsed = _parse(job)
        groups = [o for o in parsed if self._is_group(o)]
        values = [o for o in parsed if not self._is_group(o)]
        key = tuple(hydra_ovs) + tuple(o.input_line for o in groups)
        if key not in self._groups:
            full = self._compose(list(key))
            bare = copy.deepcopy(full)
            with _open(bare):
                del bare["hydra"]
            self._groups[key] = (full, bare)
        base, bare = self._groups[key]
        cfg = copy.deepcopy(bare)
        try:  # the value overrides, applied as Hydra applies them after the defaults list
            ConfigLoaderImpl._apply_overrides_to_config(values, cfg)
        except Exception as exc:
            try:  # the whole composition: Hydra's own verdict (this raises when the fast path did)
                cfg = compose(config_name=self.name, overrides=[*hydra_ovs, *job])
            except Exception:
                raise ConfigError(self.explain(exc, [*hydra_ovs, *job], base)) from None
        for o in values:
            if o.is_add() or o.is_force_add() or o.is_delete():
                continue
            declared = _node(bare, o.key_or_group)
            if declared is None or isinstance(declared, (DictConfig, ListConfig)):
                continue
            if declared._is_missing() or declared._is_interpolation():
                continue
            why = _type_mistake(o.key_or_group, declared._value(), o.value())
            if why:
                raise ConfigError(why)
        for k, v in (fill or {}).items():
            OmegaConf.update(cfg, k, v)
        if require_values:
            missing = _missing(cfg)
            if missing:
                raise ConfigError(self._missing_message(missing[0], base))
        self._check_interpolations(cfg)
        return cfg, base

    def _missing_message(self, key: str, cfg: DictConfig) -> str:
        choices = OmegaConf.select(cfg, "hydra.runtime.choices", default=None) or {}
        top = key.split(".", 1)[0]
        where = f"conf/{self.name}.yaml"
        option = choices.get(top) if top in choices else None
        if option is not None and (config_dir() / top / f"{option}.yaml").exists():
            where = f"conf/{top}/{option}.yaml ({top}={option})"
        return f"config key '{key}' needs a value (it is ??? in {where}): add {key}=..."

    @staticmethod
    def _check_interpolations(cfg: DictConfig) -> None:
        from omegaconf.errors import InterpolationKeyError

        for k in cfg.keys():
            node = cfg._get_node(k)
            try:
                if isinstance(node, (DictConfig, ListConfig)):
                    OmegaConf.to_container(node, resolve=True)
                else:
                    cfg[k]
            except InterpolationKeyError as exc:
                raise ConfigError(f"config key '{exc.full_key or k}': {str(exc.msg).splitlines()[0]}") from None
            except Exception:  # resolvers that need a running job (${hydra:...}), missing values: not ours to judge
                pass

    # ---------------------------------------------------------- explain ---
    def _base_for_keys(self, overrides: list[str]) -> DictConfig | None:
        """A config to take known keys from: the group overrides alone, else the defaults."""
        try:
            parsed = _parse(overrides)
            groups = [o.input_line for o in parsed if not o.is_sweep_override() and self._is_group(o)]
        except Exception:
            groups = []
        for ovs in (groups, []):
            try:
                return compose(config_name=self.name, overrides=ovs, return_hydra_config=True)
            except Exception:
                continue
        return None

    def _groups_of(self, base: DictConfig | None) -> list[str]:
        choices = OmegaConf.select(base, "hydra.runtime.choices", default=None) if base is not None else None
        return [str(g) for g in (choices or {}) if not str(g).startswith("hydra/")]

    def _options(self, group: str) -> list[str]:
        try:
            from hydra.core.object_type import ObjectType

            repo = GlobalHydra.instance().config_loader().repository
            return list(repo.get_group_options(group, results_filter=ObjectType.CONFIG))
        except Exception:
            return []

    def explain(self, exc: BaseException, overrides: list[str], base: DictConfig | None = None) -> str:
        """One line for a Hydra composition error, with a did-you-mean where one fits."""
        from hydra.errors import MissingConfigException, OverrideParseException
        from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

        if isinstance(exc, OverrideParseException):
            try:
                _parse(overrides)
            except ConfigError as mine:
                return str(mine)
        if isinstance(exc, MissingConfigException) and exc.missing_cfg_file and "/" in str(exc.missing_cfg_file):
            group, _, option = str(exc.missing_cfg_file).rpartition("/")
            if group == "hydra/launcher" and option.startswith("submitit_") and not _has_submitit():
                from .errors import install_hint

                return (f"hydra/launcher={option} comes from hydra-submitit-launcher, which is not installed; "
                        f"the 'cluster' extra installs it: {install_hint('cluster')}")
            options = list(exc.options or []) or self._options(group)
            return self._unknown_option(group, option, options)
        msg = str(exc).strip() or str(exc.__cause__ or "").strip()
        cause = exc.__cause__
        m = re.match(r"(?:In '[^']*': )?Could not override '([^']+)'", msg)
        if m and ("No match in the defaults list" in msg or "Did you mean to override" in msg):
            group = m.group(1)
            base = base if base is not None else self._base_for_keys(overrides)
            groups = self._groups_of(base)
            guess = _did_you_mean(group, groups)
            hint = f"; did you mean '{guess}'?" if guess else ""
            return f"config '{self.name}' has no config group '{group}'{hint or ';'} its groups: {_listing(groups)}"
        if m and isinstance(cause, (ConfigKeyError, ConfigAttributeError)):
            return self._unknown_key(m.group(1), base if base is not None else self._base_for_keys(overrides))
        m = re.match(r"Could not delete from config\. '([^']+)' does not exist", msg)
        if m:
            return self._unknown_key(m.group(1), base if base is not None else self._base_for_keys(overrides))
        m = re.match(r"Could not append to config\. An item is already at '([^']+)'", msg)
        if m:
            line = next((o for o in overrides if o.startswith(f"+{m.group(1)}=")), f"+{m.group(1)}=...")
            return f"config key '{m.group(1)}' already exists: set it without the '+' ({line[1:]})"
        m = re.match(r"Could not delete '([^']+)'\. No match in the defaults list", msg)
        if m:
            return f"config group '{m.group(1)}' is not in the defaults of config '{self.name}': nothing to delete"
        if "Config group override must be" in msg:
            for o in _parse([x for x in overrides if "=" in x]):
                if not o.is_sweep_override() and self._is_group(o) and not isinstance(o.value(), (str, list)):
                    return self._unknown_option(o.key_or_group, str(o.value()), self._options(o.key_or_group))
        m = re.match(r"Error merging override (.+)", msg)
        if m and isinstance(cause, OmegaConfBaseException):
            return f"override {m.group(1).strip()!r}: {str(cause).splitlines()[0]}"
        text = msg.split("\nConfig search path:")[0].split("\nSearch path:")[0]
        return f"config '{self.name}': {one_line(text)}"

    def _unknown_option(self, group: str, option: str, options: list[str]) -> str:
        if not option:
            return f"config group '{group}' needs an option: {group}=NAME; known: {_listing(options)}"
        guess = _did_you_mean(option, options)
        hint = f"; did you mean '{guess}'?" if guess else ";"
        return f"unknown option '{option}' for config group '{group}'{hint} known: {_listing(options)}"

    def _unknown_key(self, key: str, base: DictConfig | None) -> str:
        if base is None:
            return f"unknown config key '{key}'"
        parts = key.split(".")
        if parts[0] == "dataset" and "datasets" in base and "dataset" not in base:  # the benchmark's list
            return (f"unknown config key '{key}': this command takes datasets=[...], each a dataset option or a "
                    "dataset directory, e.g. \"datasets=[data/my_axis]\"")
        node = base
        for i, seg in enumerate(parts):
            if isinstance(node, DictConfig) and seg in node.keys():
                node = node._get_node(seg)
                continue
            where = ".".join(parts[:i])
            if not isinstance(node, DictConfig):
                return f"unknown config key '{key}': '{where}' is a value, not a section"
            known = [str(k) for k in node.keys() if i > 0 or k != "hydra" or key.startswith("hydra")]
            candidates = known + (self._groups_of(base) if i == 0 else [])
            guess = _did_you_mean(seg, candidates)
            if guess:
                full = ".".join([*parts[:i], guess, *parts[i + 1:]])
                return f"unknown config key '{key}'; did you mean '{full}'?"
            if i == len(parts) - 1:  # the same name elsewhere: a key at the wrong level
                elsewhere = [k for k in _flat_keys(base) if k.rsplit(".", 1)[-1] == seg and not k.startswith("hydra.")]
                if elsewhere:
                    return f"unknown config key '{key}'; did you mean '{elsewhere[0]}'?"
            section = f"keys of '{where}'" if where else f"keys of config '{self.name}'"
            return f"unknown config key '{key}'; {section}: {_listing(sorted(set(known)))} (a new key is added with +{key}=...)"
        return f"unknown config key '{key}'"


def group_option(group: str, name: str) -> dict:
    """The plain config of option ``name`` of group ``group`` (``conf/<group>/<name>.yaml``)."""
    path = config_dir() / group / f"{name}.yaml"
    if not path.exists():
        known = sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))
        raise ExperimentError(f"config key '{group}': no option {name!r}; known: {known}")
    return OmegaConf.to_container(OmegaConf.load(path), resolve=True)


def _parameters(target) -> list[str] | None:
    """The keyword parameters ``target`` (a class or function) takes; None when it takes any
    (``**kwargs``) or its signature cannot be read."""
    import inspect

    try:
        sig = inspect.signature(target)
    except (TypeError, ValueError):
        return None
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in sig.parameters.values()):
        return None
    return [n for n, p in sig.parameters.items() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]


def check_targets(node, key: str) -> None:
    """Every ``_target_`` in the config ``node`` (at config key ``key``) can be imported and
    takes the keys given with it, checked before anything is instantiated: a typo such as
    ``+model.bogus=1`` is an :class:`ExperimentError` naming the key and the parameters
    there are, not Hydra's ``TypeError`` traceback from inside the constructor."""
    import difflib

    from hydra._internal.utils import _locate  # what instantiate() uses, without its error log

    if isinstance(node, Mapping):
        target = node.get("_target_")
        if target is not None:
            try:
                obj = _locate(str(target))
            except Exception as exc:
                why = exc.__cause__ or exc
                raise ExperimentError(f"config key '{key}._target_': cannot import {target!r}: {why}") from None
            names = _parameters(obj)
            given = [str(k) for k in node if not (str(k).startswith("_") and str(k).endswith("_"))]
            bad = [k for k in given if names is not None and k not in names]
            if bad:
                owner = getattr(obj, "__name__", str(target))
                near = difflib.get_close_matches(bad[0], names, n=1)
                hint = f" (did you mean {near[0]!r}?)" if near else ""
                raise ExperimentError(f"config key '{key}.{bad[0]}': {owner} has no parameter {bad[0]!r}{hint}; "
                                      f"its parameters: {', '.join(names)}")  # fmt: skip
        for k, v in node.items():
            if not str(k).startswith("_"):
                check_targets(v, f"{key}.{k}")
    elif isinstance(node, (list, tuple)):
        for i, v in enumerate(node):
            check_targets(v, f"{key}[{i}]")
