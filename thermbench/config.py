"""Locate ``conf/`` and compose Hydra configs (no hand-rolled config parsing)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig


class ConfigError(ValueError):
    """A config or override is wrong; the message names the key."""


def config_dir() -> Path:
    """``$THERMBENCH_CONFIG_DIR``, else the ``conf/`` next to the package (a source checkout)."""
    env = os.environ.get("THERMBENCH_CONFIG_DIR")
    cand = Path(env) if env else Path(__file__).resolve().parent.parent / "conf"
    if not (cand / "simulate.yaml").exists():
        raise ConfigError(
            f"config directory {cand} has no simulate.yaml; set THERMBENCH_CONFIG_DIR to the project's conf/"
        )
    return cand


def load_config(name: str = "simulate", overrides: Sequence[str] = (), return_hydra_config: bool = False) -> DictConfig:
    """Compose ``conf/<name>.yaml`` with Hydra overrides (``key=value``, ``group=option``).

    ``return_hydra_config=True`` keeps the ``hydra`` node (its ``runtime.choices`` name
    the options picked for each group), as a ``hydra.main`` job sees it."""
    if GlobalHydra.instance().is_initialized():
        GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(config_dir())):
            return compose(config_name=name, overrides=list(overrides), return_hydra_config=return_hydra_config)
    except ConfigError:
        raise
    except Exception as exc:  # hydra's override/composition errors are user mistakes
        raise ConfigError(f"config {name!r} with overrides {list(overrides)}: {exc}") from None


def with_defaults(name: str, cfg) -> dict:
    """``cfg`` (a mapping, e.g. from a test or a notebook) over the defaults of
    ``conf/<name>.yaml``, as a plain dict; a key the config does not have is an error."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    base = load_config(name)
    plain = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg or {})
    try:
        merged = OmegaConf.merge(base, OmegaConf.create(plain))
        return OmegaConf.to_container(merged, resolve=True)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None)
        raise ConfigError(f"config {name!r}: key {key!r}: {str(exc).splitlines()[0]}") from None
