"""Every effect by id: the canonical library (:data:`~thermbench.sim.effects.EFFECTS`) and the
open terms (:data:`~thermbench.sim.open_terms.OPEN_TERMS`), looked up and built from ids and
configs (:func:`make_effect`, :func:`effects_from_config`), with one-line config errors.
"""

from __future__ import annotations

import math
from dataclasses import fields
from numbers import Real
from typing import Mapping

from .effects import EFFECTS, Effect
from .open_terms import OPEN_TERMS


def effect_class(effect_id: str) -> type[Effect]:
    """The class of a canonical effect or an open term (a ConfigError when it is neither)."""
    cls = EFFECTS.get(effect_id) or OPEN_TERMS.get(effect_id)
    if cls is None:
        raise _config_error(f"unknown effect {effect_id!r}; the canonical effects are {sorted(EFFECTS)}, "
                            f"the open terms {sorted(OPEN_TERMS)}")  # fmt: skip
    return cls


def _config_error(message: str):
    """A :class:`thermbench.config.ConfigError` (a user's mistake, one line); imported here,
    not at the top, so the physics loads without Hydra."""
    from ..config import ConfigError

    return ConfigError(message)


def make_effect(effect_id: str, **params) -> Effect:
    """Build a canonical effect by id; unknown ids or parameters give a clear error
    (a :class:`~thermbench.config.ConfigError`: effect ids and parameters come from configs)."""
    cls = effect_class(effect_id)
    known = {f.name for f in fields(cls)}
    bad = set(params) - known
    if bad:
        raise _config_error(f"effect {effect_id!r} has no parameter(s) {sorted(bad)}; it takes {sorted(known)}")
    return cls(**params)


def effects_from_config(cfg, key: str = "effects") -> list[Effect]:
    """``{effect_id: {enabled: bool, param: value, ...}}`` -> list of enabled effects.

    A bare ``effect_id: true/false`` also works. A mistake (an unknown effect or parameter,
    a value that is not a finite number) is a :class:`~thermbench.config.ConfigError`
    naming the config key ``<key>.<effect>[.<param>]``.
    """
    out: list[Effect] = []
    for effect_id, spec in dict(cfg or {}).items():
        where = f"{key}.{effect_id}"
        if isinstance(spec, bool):
            spec = {"enabled": spec}
        if spec is not None and not isinstance(spec, Mapping):
            raise _config_error(f"config key {where!r}: expected true/false or {{param: value}}, got {spec!r}")
        spec = dict(spec or {})
        if not spec.pop("enabled", True):
            continue
        if effect_id not in EFFECTS and effect_id not in OPEN_TERMS:
            raise _config_error(f"config key {where!r}: unknown effect {effect_id!r}; the canonical effects are "
                                f"{sorted(EFFECTS)}, the open terms {sorted(OPEN_TERMS)}")  # fmt: skip
        cls = effect_class(effect_id)
        known = sorted(f.name for f in fields(cls))
        for param, value in spec.items():
            if param not in known:
                raise _config_error(f"config key '{where}.{param}': effect {effect_id!r} has no parameter(s) "
                                    f"{[param]}; it takes {known}")  # fmt: skip
            if param == cls.choice:
                if not isinstance(value, str) or not value:
                    raise _config_error(f"config key '{where}.{param}': expected a signal name ('speed' or a "
                                        f"temperature sensor), got {value!r}")  # fmt: skip
                continue
            if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value):
                raise _config_error(f"config key '{where}.{param}': expected a finite number, got {value!r}")
        out.append(make_effect(str(effect_id), **spec))
    return out
