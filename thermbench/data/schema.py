"""The dataset contract's ``metadata.yaml`` as pydantic models (docs/dataset-format.md)."""

from __future__ import annotations

import numbers
from typing import Annotated, Literal, Optional

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from . import limits
from .errors import short_repr
from .limits import Quantity

FORMAT_V1 = "thermbench-dataset/1"
FORMAT_V2 = "thermbench-dataset/2"
FORMAT = FORMAT_V1  # what datasets of ball-screw runs are written as (the simulator's)
FORMATS = (FORMAT_V1, FORMAT_V2)
PARTS = ("axis", "spindle")
# operating inputs the contract names (process columns); a v2 dataset may declare others
OPERATING_INPUTS = {"feed_mm_min": limits.FEED_MM_MIN, "spindle_rpm": limits.SPINDLE_RPM, "load_N": limits.LOAD_N}
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
    axis: Optional[str] = None  # required in format 1 (the axis its runs move)


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
    """A run's loading state. Format 1: the stroke and feed of seed 002 Table 5 (all four
    keys). Format 2: any operating levels (``spindle_rpm: 2500``), the four keys optional;
    every extra key must be a finite number."""

    stroke_mm: Optional[Stroke_mm] = None
    start_mm: Optional[Position_mm] = None
    end_mm: Optional[Position_mm] = None
    feed_mm_min: Optional[Feed_mm_min] = None

    @model_validator(mode="after")
    def _levels(self) -> "Condition":
        for key, value in (self.model_extra or {}).items():
            q = OPERATING_INPUTS.get(key)
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise ValueError(f"condition {key!r}: expected a number (an operating level), got {short_repr(value)}")
            problem = (q or limits.Quantity("", -1e12, 1e12)).problem(float(value))
            if problem is not None:
                raise ValueError(f"condition {key!r}: {problem}")
        return self

    def levels(self) -> dict[str, float]:
        """The declared levels, one number per key (what groups runs into loading states)."""
        out = {k: getattr(self, k) for k in ("stroke_mm", "start_mm", "end_mm", "feed_mm_min")}
        out.update(self.model_extra or {})
        return {k: float(v) for k, v in out.items() if v is not None}


class RunMeta(_Model):
    condition: Optional[Condition] = None  # required in format 1; format 2: derived when absent
    notes: Optional[str] = None
    # format 2, runs without a declared condition: names for the segments derived from the
    # operating signal (data/segments.py), in time order; default s01_<level>, ...
    segments: Optional[list[str]] = None


class _ConditionV1(_Model):
    stroke_mm: Stroke_mm
    start_mm: Position_mm
    end_mm: Position_mm
    feed_mm_min: Feed_mm_min


class _RunMetaV1(_Model):
    condition: _ConditionV1
    notes: Optional[str] = None


class MetadataV1(_Model):
    """Format 1 as it is checked on input: every key required (the messages name it)."""

    format: str
    machine: "_MachineV1"
    screw: ScrewMeta
    material: MaterialMeta
    sensors: dict[str, str]
    runs: dict[str, _RunMetaV1]


class _MachineV1(_Model):
    name: str
    axis: str


class ChannelMeta(_Model):
    """One error channel (format 2): what a column of readings measures.

    ``kind``: ``along_axis`` (readings at commanded positions ``target_mm``: an
    interferometer along a linear axis, ISO 230-2) or ``fixed_point`` (a displacement at
    one point: the spindle nose or a test mandrel, ISO 230-3 X1, X2, Y1, Y2, Z).
    ``direction``: X, Y or Z for a displacement (µm), A, B or C for a tilt about that
    axis (µrad)."""

    kind: Literal["along_axis", "fixed_point"]
    direction: Literal["X", "Y", "Z", "A", "B", "C"]
    location: str
    unit: Literal["um", "urad"] = "um"
    position_mm: Optional[Position_mm] = None  # e.g. the probe's position along the mandrel

    @model_validator(mode="after")
    def _unit(self) -> "ChannelMeta":
        want = "urad" if self.direction in ("A", "B", "C") else "um"
        if self.unit != want:
            raise ValueError(f"direction {self.direction} is measured in {want}, not {self.unit}")
        return self


class SamplingMeta(_Model):
    max_gap_s: Optional[_quantity(limits.MAX_GAP_S)] = None  # largest step in process t_s


class SegmentationMeta(_Model):
    """How runs without a condition are split into segments (format 2; the defaults of
    :func:`thermbench.data.segments.derive_segments` for what is left out)."""

    stop_below: Optional[float] = Field(None, ge=0)  # operating value at or below which the machine is stopped
    window_s: Optional[_quantity(limits.MAX_GAP_S)] = None  # moving-median window
    min_duration_s: Optional[_quantity(limits.MAX_GAP_S)] = None  # shortest period, stop or level that counts
    rel_tol: Optional[float] = Field(None, gt=0, lt=1)  # relative tolerance of a level

    def kwargs(self) -> dict:
        return {k: v for k, v in self.model_dump().items() if v is not None and k in
                ("stop_below", "window_s", "min_duration_s", "rel_tol")}  # fmt: skip


class ReferenceMeta(_Model):
    """Where the thermal error of a reading is counted from (format 2).

    ``cold_cycle``: the run's first measuring cycle (format 1's rule, seed 002 §3.1);
    ``first_reading``: each channel's (and target's, direction's) first reading;
    ``time``: the readings at ``t_s`` of each run (linear interpolation between readings)."""

    mode: Literal["cold_cycle", "first_reading", "time"] = "cold_cycle"
    t_s: Optional[_quantity(limits.TIME_S)] = None

    @model_validator(mode="after")
    def _time(self) -> "ReferenceMeta":
        if self.mode == "time" and self.t_s is None:
            raise ValueError("mode 'time' needs t_s, the reference time in seconds on the run's clock")
        if self.mode != "time" and self.t_s is not None:
            raise ValueError(f"t_s is used only with mode 'time', not {self.mode!r}")
        return self


class Metadata(_Model):
    """``metadata.yaml``, format 1 (a ball-screw axis, one interferometer channel) or
    format 2 (any machine part, several error channels, derived conditions)."""

    format: str
    machine: MachineMeta
    screw: Optional[ScrewMeta] = None  # format 1: required; format 2: the screw physics model needs it
    material: Optional[MaterialMeta] = None
    sensors: dict[str, str]
    runs: dict[str, RunMeta]
    # format 2 only
    parts: Optional[list[Literal["axis", "spindle"]]] = None
    channels: Optional[dict[str, ChannelMeta]] = None
    operating: Optional[list[str]] = None
    sampling: Optional[SamplingMeta] = None
    reference: Optional[ReferenceMeta] = None
    segmentation: Optional[SegmentationMeta] = None

    @model_validator(mode="after")
    def _check(self) -> "Metadata":
        if self.format not in FORMATS:
            raise ValueError(f"format must be one of {list(FORMATS)}, got {self.format!r}")
        if not self.runs:
            raise ValueError("runs: at least one run is needed")
        if self.format == FORMAT_V1:
            self._check_v1()
        else:
            self._check_v2()
        return self

    def _check_v1(self) -> None:
        missing = [k for k in ("screw", "material") if getattr(self, k) is None]
        if self.machine.axis is None:
            missing.insert(0, "machine.axis")
        for run_id, run in self.runs.items():
            if run.condition is None:
                missing.append(f"runs.{run_id}.condition")
            else:
                missing += [f"runs.{run_id}.condition.{k}" for k in ("stroke_mm", "start_mm", "end_mm", "feed_mm_min")
                            if getattr(run.condition, k) is None]  # fmt: skip
        if missing:
            raise ValueError(f"{missing[0]}: missing (required in {FORMAT_V1}; {FORMAT_V2} makes it optional)")
        v2_only = [k for k in ("parts", "channels", "operating", "sampling", "reference", "segmentation")
                   if getattr(self, k) is not None]
        v2_only += [f"runs.{r}.segments" for r, run in self.runs.items() if run.segments is not None]
        if v2_only:
            raise ValueError(f"{v2_only[0]}: a key of {FORMAT_V2}; write format: {FORMAT_V2}")

    def _check_v2(self) -> None:
        if not self.parts:
            raise ValueError(f"parts: missing; list what the dataset is a test of, any of {list(PARTS)}")
        if len(set(self.parts)) != len(self.parts):
            raise ValueError(f"parts: {self.parts} names a part twice")
        if self.screw is not None and "axis" not in self.parts:
            raise ValueError("screw: a screw block describes a linear axis; add 'axis' to parts")
        if self.channels is not None:
            for name, ch in self.channels.items():
                problem = limits.run_id_problem(name)
                if problem is not None:
                    raise ValueError(f"channels: channel name {short_repr(name)} {problem}; names follow the run-id rule")
                if ch.kind == "along_axis" and "axis" not in self.parts:
                    raise ValueError(f"channels.{name}: kind along_axis measures along a linear axis; add 'axis' to parts")
        for col in self.operating_inputs():
            if col in ("t_s", "run_id", "axis_mm") or col.endswith("_C") and col[:-2] in self.sensors:
                raise ValueError(f"operating: {col!r} is not an operating input (a time, position or temperature)")
        for run_id, run in self.runs.items():
            if run.segments is not None:
                if run.condition is not None:
                    raise ValueError(f"runs.{run_id}.segments: names derived segments; this run declares a condition")
                for name in run.segments:
                    problem = limits.run_id_problem(name)
                    if problem is not None:
                        raise ValueError(f"runs.{run_id}.segments: segment name {short_repr(name)} {problem}")
                if len(set(run.segments)) != len(run.segments):
                    raise ValueError(f"runs.{run_id}.segments: a name appears twice")

    # --- what the rest of thermbench asks -------------------------------------
    @property
    def version(self) -> int:
        return 1 if self.format == FORMAT_V1 else 2

    @property
    def has_axis(self) -> bool:
        return self.version == 1 or "axis" in (self.parts or ())

    @property
    def has_spindle(self) -> bool:
        return "spindle" in (self.parts or ())

    def operating_inputs(self) -> list[str]:
        """Process columns that drive the machine: declared, else by part (format 1: feed)."""
        if self.operating is not None:
            return list(self.operating)
        out = []
        if self.has_axis:
            out.append("feed_mm_min")
        if self.has_spindle:
            out.append("spindle_rpm")
        return out

    def error_channels(self) -> dict[str, ChannelMeta]:
        """The error channels; format 1 has one, along its axis, named after the axis."""
        if self.channels is not None:
            return dict(self.channels)
        if self.version == 1:
            axis = str(self.machine.axis)
            direction = axis.upper() if axis.upper() in ("X", "Y", "Z") else "X"
            return {axis: ChannelMeta(kind="along_axis", direction=direction, location="axis")}
        return {}

    def reference_mode(self) -> ReferenceMeta:
        return self.reference if self.reference is not None else ReferenceMeta()

    def sensor_column(self, sensor: str) -> str:
        return f"{sensor}_C"


MetadataV1.model_rebuild()
