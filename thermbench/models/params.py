"""Hyper-parameter checks of the model families, as pydantic models.

Every family keeps scikit-learn's contract: the constructor only stores its parameters
(so ``get_params``/``set_params``/``clone`` work) and ``fit`` checks them. The check is
one pydantic model per family (``<Family>Params``, next to the family), validated by
:func:`check_params` against ``estimator.get_params(deep=False)``. A bad value is a
:class:`~thermbench.models.base.ModelError` in one line that names ``<Family>.<param>``,
what was expected and what was given::

    PSOLSSVM.n_particles: expected an integer >= 1, got 0

The types here are strict, as the hand-written checks they replace were: a bool is not
an integer or a number, a string is not a number, NaN and inf are not finite numbers;
numpy scalars (``np.int64(3)``, ``np.float32(0.5)``) count as the Python numbers they hold.
Constraints are ``annotated_types`` markers (``Ge``, ``Gt``, ``Le``, ``Lt``) on these
types; the "expected ..." text of a message is derived from them, or given by an
:class:`Expect` marker where a type says more than a number range.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Mapping, Sequence
from typing import Annotated, Any, Literal, Optional, TypeVar, Union

import numpy as np
from annotated_types import Ge, Gt, Le, Lt
from pydantic import AfterValidator, AllowInfNan, BaseModel, BeforeValidator, ConfigDict, Strict, ValidationError

from ..data.errors import short_repr
from .base import ModelError

__all__ = [
    "Bool",
    "Degree",
    "Expect",
    "Int",
    "Limit",
    "Number",
    "Params",
    "PositiveNumber",
    "Seed",
    "Selection",
    "SensorNames",
    "check_params",
    "expected",
    "pair_bounds",
    "validate",
]


class Expect:
    """``Annotated`` marker: what a message says the parameter expects (when the type
    and its constraints do not say it well, e.g. a pair of bounds)."""

    def __init__(self, text: str) -> None:
        self.text = text

    def __repr__(self) -> str:
        return f"Expect({self.text!r})"


def _plain(value):
    """A numpy scalar as the Python scalar it holds (np.int64 -> int, np.bool_ -> bool)."""
    return value.item() if isinstance(value, np.generic) else value


#: an integer (a bool is not one, nor a string or a float such as 3.0)
Int = Annotated[int, Strict(), BeforeValidator(_plain)]
#: a finite number (int or float; not a bool, a string, NaN or inf)
Number = Annotated[float, Strict(), AllowInfNan(False), BeforeValidator(_plain)]
#: true or false (not 0/1, not "yes")
Bool = Annotated[bool, Strict(), BeforeValidator(_plain)]


def _not_nan(x: float) -> float:
    if x != x:
        raise ValueError("NaN")
    return x


#: a bound of a search: a number, or -inf/inf for none (not NaN)
Limit = Annotated[float, Strict(), BeforeValidator(_plain), AfterValidator(_not_nan)]
PositiveNumber = Annotated[Number, Gt(0)]
Degree = Annotated[Int, Ge(0)]  # a polynomial degree
Seed = Annotated[Int, Ge(0), Le(2**32 - 1)]  # what numpy's and torch's generators take
#: a sensor name or a list of them (a lone name is one sensor)
SensorNames = Annotated[Union[str, Sequence[str]], Expect("a sensor name or a list of sensor names")]
#: options of the sensitive-point selection (thermbench.models.sensor_choice.choose_sensors)
Selection = Annotated[Optional[Mapping[str, Any]], Expect("None or a mapping of selection options")]


def _check_pair(strict: bool):
    def check(pair: tuple[float, float]) -> tuple[float, float]:
        lo, hi = pair
        if not (lo < hi if strict else lo <= hi):
            raise ValueError("low above high" if lo > hi else "low equal to high")
        return pair

    return check


def pair_bounds(strict: bool = True) -> Any:
    """A pair ``(lo, hi)`` of finite numbers with ``0 < lo < hi`` (``lo <= hi`` when not
    ``strict``: equal bounds fix the value), as a tuple of floats."""
    rel = "<" if strict else "<="
    return Annotated[
        tuple[PositiveNumber, PositiveNumber],
        AfterValidator(_check_pair(strict)),
        Expect(f"a pair (low, high) of finite numbers with 0 < low {rel} high"),
    ]


class Params(BaseModel):
    """Base of the families' parameter models: arbitrary objects allowed (estimators,
    filters), unknown keys ignored (a subclass of a family may add parameters), frozen."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="ignore", frozen=True)


P = TypeVar("P", bound=Params)


# --------------------------------------------------------------- messages ---
_NUMBER = {int: "an integer", float: "a finite number", bool: "true or false", str: "a string"}


def _fmt(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _describe(tp) -> str | None:
    """What type annotation ``tp`` accepts, in words (None when it cannot say)."""
    origin = typing.get_origin(tp)
    if origin is Annotated:
        base, *meta = typing.get_args(tp)
        for m in meta:
            if isinstance(m, Expect):
                return m.text
        what = _describe(base)
        if what is None:
            return None
        lo = hi = None  # (bracket, value) of the lower and upper bound
        for m in meta:
            if isinstance(m, Ge):
                lo = ("[", m.ge)
            elif isinstance(m, Gt):
                lo = ("(", m.gt)
            elif isinstance(m, Le):
                hi = ("]", m.le)
            elif isinstance(m, Lt):
                hi = (")", m.lt)
        if lo and hi:
            if base is int and lo[0] == "[" and hi[0] == "]":
                return f"{what} {_fmt(lo[1])}..{_fmt(hi[1])}"
            return f"{what} in {lo[0]}{_fmt(lo[1])}, {_fmt(hi[1])}{hi[0]}"
        if lo:
            return f"{what} {'>=' if lo[0] == '[' else '>'} {_fmt(lo[1])}"
        if hi:
            return f"{what} {'<=' if hi[0] == ']' else '<'} {_fmt(hi[1])}"
        return what
    if origin in (Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        parts = [_describe(a) for a in args]
        if any(p is None for p in parts):
            return None
        text = " or ".join(parts)
        return f"None or {text}" if len(args) < len(typing.get_args(tp)) else text
    if origin is Literal:
        return f"one of {list(typing.get_args(tp))}"
    if origin in (dict, Mapping):
        return "a mapping"
    if tp in _NUMBER:
        return _NUMBER[tp]
    return None


def expected(model: type[Params], key: str) -> str | None:
    """What parameter ``key`` of ``model`` expects, in words (``"an integer >= 1"``)."""
    field = model.model_fields.get(key)
    if field is None:
        return None
    if field.description:
        return field.description
    tp = field.annotation
    if field.metadata:
        tp = Annotated[(tp, *field.metadata)]
    return _describe(tp)


def _given(value) -> str:
    """The value a message reports: its repr for plain data, the type of anything else."""
    v = _plain(value)
    if v is None or isinstance(v, (bool, int, float, str, bytes, list, tuple, dict, set)):
        return short_repr(v)
    if isinstance(v, (Sequence, Mapping)):  # a ListConfig/DictConfig: its content
        return short_repr(list(v) if isinstance(v, Sequence) else dict(v))
    return f"a {type(v).__name__}"


def validate(model: type[P], values: Mapping[str, Any], owner: str) -> P:
    """``model`` validated from ``values``; a :class:`ModelError` naming ``<owner>.<key>``,
    what the key expects and the value given when one is wrong (the first, in field order)."""
    try:
        return model.model_validate(dict(values))
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = err.get("loc") or ()
        if not loc:  # a check across parameters (a model validator): its own message
            ctx = err.get("ctx") or {}
            raise ModelError(f"{owner}: {ctx.get('error', err['msg'])}") from None
        key = str(loc[0])
        what = expected(model, key)
        what = f"expected {what}" if what else err["msg"]
        raise ModelError(f"{owner}.{key}: {what}, got {_given(values.get(key))}") from None


def check_params(estimator, model: type[P], **override) -> P:
    """The parameters of ``estimator`` (``get_params(deep=False)``, with ``override``)
    validated by ``model``; a bad one is a :class:`ModelError` naming ``<Family>.<key>``."""
    values = {k: v for k, v in estimator.get_params(deep=False).items() if k in model.model_fields}
    values.update(override)
    return validate(model, values, type(estimator).__name__)
