"""The dataset contract's ``metadata.yaml`` as pydantic models (docs/dataset-format.md)."""

from __future__ import annotations

import numbers
from typing import Annotated, Literal, Optional

from pydantic import BaseModel, BeforeValidator, ConfigDict, ValidationInfo, field_validator, model_validator

from . import limits
from .errors import short_repr
from .limits import Quantity

FORMAT = "thermbench-dataset/1"
KNOWN_LOCATIONS = (
    "ambient",
    "fixed_bearing_housing",
    "nut_housing",
    "free_bearing_housing",
    "motor",
    "bed",
)


def _quantity(q: Quantity):
    """A float field that must be a finite number in ``q``'s plausible range; the
    message names the unit (and the unit mistake an implausible value suggests)."""

    def check(value):
        if isinstance(value, bool) or not isinstance(value, (numbers.Real, str)):
            raise ValueError(f"expected a number of {q.unit}, got {short_repr(value)}")
        try:
            number = float(value.strip() if isinstance(value, str) else value)
        except (ValueError, OverflowError):
            raise ValueError(f"expected a number of {q.unit}, got {short_repr(value)}") from None
        problem = q.problem(number)
        if problem is not None:
            raise ValueError(problem)
        return number

    return Annotated[float, BeforeValidator(check)]


Length_m = _quantity(limits.LENGTH_M)
Diameter_m = _quantity(limits.DIAMETER_M)
BearingLength_m = _quantity(limits.BEARING_LENGTH_M)
Position_mm = _quantity(limits.POSITION_MM)
Stroke_mm = _quantity(limits.STROKE_MM)
Feed_mm_min = _quantity(limits.FEED_MM_MIN)
Alpha_per_K = _quantity(limits.ALPHA_PER_K)
Density_kg_m3 = _quantity(limits.DENSITY_KG_M3)
HeatCapacity_J_kgK = _quantity(limits.HEAT_CAPACITY_J_KGK)


class _Model(BaseModel):
    model_config = ConfigDict(extra="allow", allow_inf_nan=False)


class MachineMeta(_Model):
    name: str
    axis: str


class ScrewMeta(_Model):
    length_m: Length_m
    diameter_m: Diameter_m
    nut_length_m: Length_m
    fixed_bearing_length_m: BearingLength_m
    mounting: Literal["fixed_free", "fixed_supported", "fixed_fixed"]
    fixed_end_axis_mm: Optional[Position_mm] = None  # seed 000 Pf, identified when absent

    @field_validator("nut_length_m", "fixed_bearing_length_m")
    @classmethod
    def _shorter_than_screw(cls, value: float, info: ValidationInfo) -> float:
        length = info.data.get("length_m")
        if length is not None and value >= length:
            raise ValueError(f"{info.field_name} {value:.6g} m must be shorter than the screw (length_m {length:.6g} m)")
        return value


class MaterialMeta(_Model):
    alpha_per_K: Alpha_per_K
    density_kg_m3: Density_kg_m3
    heat_capacity_J_kgK: HeatCapacity_J_kgK


class Condition(_Model):
    stroke_mm: Stroke_mm
    start_mm: Position_mm
    end_mm: Position_mm
    feed_mm_min: Feed_mm_min


class RunMeta(_Model):
    condition: Condition
    notes: Optional[str] = None


class Metadata(_Model):
    format: str
    machine: MachineMeta
    screw: ScrewMeta
    material: MaterialMeta
    sensors: dict[str, str]
    runs: dict[str, RunMeta]

    @model_validator(mode="after")
    def _check(self) -> "Metadata":
        if self.format != FORMAT:
            raise ValueError(f"format must be {FORMAT!r}, got {self.format!r}")
        if not self.runs:
            raise ValueError("runs: at least one run is needed")
        return self

    def sensor_column(self, sensor: str) -> str:
        return f"{sensor}_C"
