"""The ``conf/compensator.yaml`` keys the cycle logic uses, read and checked (:class:`Settings`).

A mistake in them is a :func:`config_error`: a :class:`~.errors.CompensatorError` naming the
config key (one line, exit 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

from .errors import CompensatorError


def config_error(message: str) -> Exception:
    """A mistake in ``conf/compensator.yaml`` or its overrides: a
    :class:`~.errors.CompensatorError` (one line, exit 2)."""
    return CompensatorError(message)


def _num(cfg: Mapping[str, Any], key: str, default: float, positive: bool = True, name: str | None = None) -> float:
    """``cfg[key]`` (else ``default``) as a number (> 0 when ``positive``); a mistake names
    the config key ``name`` (default ``key``; give the full key for a sub-mapping, e.g.
    ``_num(cfg["line"], "n_points", 21, name="line.n_points")``)."""
    name = key if name is None else name
    v = cfg.get(key, default)
    try:
        if isinstance(v, bool):
            raise TypeError
        v = float(v)
    except (TypeError, ValueError):
        raise config_error(f"config key {name!r}: expected a number, got {v!r}") from None
    if math.isnan(v) or (not positive and math.isinf(v)):
        raise config_error(f"config key {name!r}: expected a finite number, got {v}")
    if positive and not v > 0:
        raise config_error(f"config key {name!r}: must be > 0, got {v}")
    return v


def _pair(v: Any, key: str) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in v)
    except (TypeError, ValueError):
        raise config_error(f"config key {key!r}: expected [low, high], got {v!r}") from None
    if not hi > lo:
        raise config_error(f"config key {key!r}: expected [low, high] with high > low, got [{lo}, {hi}]")
    return lo, hi


def _count(cfg: Mapping[str, Any], key: str, default: int, name: str) -> int:
    """``cfg[key]`` as a whole number (``21``, ``21.0``), naming the config key ``name``."""
    v = _num(cfg, key, default, positive=False, name=name)
    if v != int(v):
        raise config_error(f"config key {name!r}: expected a whole number, got {cfg.get(key, default)!r}")
    return int(v)


@dataclass
class Settings:
    """The ``conf/compensator.yaml`` keys the cycle logic uses (see there)."""

    rate_limit_um_s: float = 20.0
    stale_after_s: float = 2.0
    max_age_s: float | None = None
    input_max_age_s: float = 10.0
    clock: str = "source"
    convention: str = "compensation"
    line_travel_mm: tuple[float, float] | None = None
    line_points: int = 21
    line_ref_mm: float | None = None
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    probe: Any = None  # thermbench.bench.adapt.ProbeParams of the probe filter (config key probe)
    bound_um: float | None = None  # the compensation's magnitude at most this (None: the manifest's faults.bounds.max_um)
    extrapolation: str = "report"  # outside the training envelope: report (flag only) | hold the last value inside
    # | limit: the interval's inner edge (manifest 'interval': the prediction moved toward 0 by its half-width)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> "Settings":
        line = dict(cfg.get("line") or {})
        travel = line.get("travel_mm")
        s = cls(rate_limit_um_s=_num(cfg, "rate_limit_um_s", 20.0), stale_after_s=_num(cfg, "stale_after_s", 2.0),
                max_age_s=None if cfg.get("max_age_s") is None else _num(cfg, "max_age_s", 0.0),
                input_max_age_s=_num(cfg, "input_max_age_s", 10.0), clock=str(cfg.get("clock", "source")),
                convention=str(cfg.get("convention", "compensation")),
                line_travel_mm=None if travel is None else _pair(travel, "line.travel_mm"),
                line_points=_count(line, "n_points", 21, "line.n_points"),
                line_ref_mm=None if line.get("ref_mm") is None else _num(line, "ref_mm", 0.0, False, "line.ref_mm"),
                ranges={k: _pair(v, f"ranges.{k}") for k, v in (cfg.get("ranges") or {}).items()},
                probe=_probe_params(cfg.get("probe")), extrapolation=str(cfg.get("extrapolation", "report")),
                bound_um=None if cfg.get("bound_um") is None else _num(cfg, "bound_um", 0.0))  # fmt: skip
        if s.convention not in ("compensation", "error"):
            raise config_error(f"config key 'convention': expected compensation or error, got {s.convention!r}")
        if s.clock not in ("source", "client"):
            raise config_error(f"config key 'clock': expected source or client, got {s.clock!r}")
        if s.line_points < 2:
            raise config_error(f"config key 'line.n_points': at least 2, got {s.line_points}")
        if s.extrapolation not in ("report", "hold", "limit"):
            raise config_error(f"config key 'extrapolation': expected report, hold or limit, got {s.extrapolation!r}")
        return s

    def range_of(self, name: str) -> tuple[float, float]:
        key = "temperature_C" if name.endswith("_C") else name
        return self.ranges.get(key, (-math.inf, math.inf))


def _probe_params(cfg):
    """:class:`thermbench.bench.adapt.ProbeParams` of config key ``probe`` (null: the defaults)."""
    from ..bench.adapt import ProbeParams, ProbeParamsError

    try:
        return ProbeParams.from_config(cfg)
    except ProbeParamsError as exc:
        raise config_error(str(exc)) from None
