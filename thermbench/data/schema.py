"""The dataset contract's ``metadata.yaml`` as pydantic models (docs/dataset-format.md)."""

from __future__ import annotations

from typing import Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, model_validator

FORMAT = "thermbench-dataset/1"
KNOWN_LOCATIONS = (
    "ambient",
    "fixed_bearing_housing",
    "nut_housing",
    "free_bearing_housing",
    "motor",
    "bed",
)


class _Model(BaseModel):
    model_config = ConfigDict(extra="allow")


class MachineMeta(_Model):
    name: str
    axis: str


class ScrewMeta(_Model):
    length_m: float = Field(gt=0)
    diameter_m: float = Field(gt=0)
    nut_length_m: float = Field(gt=0)
    fixed_bearing_length_m: float = Field(ge=0)
    mounting: Literal["fixed_free", "fixed_supported", "fixed_fixed"]
    fixed_end_axis_mm: Optional[float] = None  # seed 000 Pf, identified when absent


class MaterialMeta(_Model):
    alpha_per_K: float = Field(gt=0)
    density_kg_m3: float = Field(gt=0)
    heat_capacity_J_kgK: float = Field(gt=0)


class Condition(_Model):
    stroke_mm: float = Field(ge=0)
    start_mm: float
    end_mm: float
    feed_mm_min: float = Field(ge=0)


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
