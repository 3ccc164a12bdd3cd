"""Timing a parsed program: feeds and distances to the planned process log (``t_s, axis_mm,
feed_mm_min`` every ``sample_s``, :func:`plan_motion`), the planned dataset a model reads
(:func:`planned_dataset`) and the thermal error it predicts at each move's end
(:func:`predict_thermal_errors`).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from ..data.dataset import Dataset
from ..data.schema import FORMAT, Metadata
from ..models.base import ModelError, ThermalErrorModel
from .program import MOTION_COLUMNS, PrecompError, Program, RUN_ID


# ------------------------------------------------------------------- timing ---
def _check_positive(name: str, value, upper: float | None = None) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise PrecompError(f"{name}: expected a number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0) or (upper is not None and v > upper):
        bound = f" and <= {upper:g}" if upper is not None else ""
        raise PrecompError(f"{name}: expected a finite number > 0{bound}, got {value!r}")
    return v


def _sample(t_w: np.ndarray, x_w: np.ndarray, feed_seg: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (linear within a segment) and feed (of the segment in force; 0 after
    the last one) at ``t_s`` of a piecewise-linear motion through waypoints."""
    x = np.interp(t_s, t_w, x_w)
    k = np.searchsorted(t_w, t_s, side="right") - 1
    f = np.where((k >= 0) & (k < feed_seg.size), feed_seg[np.clip(k, 0, max(feed_seg.size - 1, 0))], 0.0)
    return x, f


def _waypoints(moves: pd.DataFrame, start_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, axis position) at every segment end with the feed of each segment, from the moves table."""
    timed = moves[moves["duration_s"] > 0]
    x0 = float(moves["axis_start_mm"].iloc[0])
    t_w = np.r_[start_s, timed["t_end_s"].to_numpy()]
    x_w = np.r_[x0, timed["axis_target_mm"].to_numpy()]
    return t_w, x_w, timed["feed_mm_min"].to_numpy()


def plan_motion(
    program: Program,
    rapid_mm_min: float = 10000.0,
    sample_s: float = 1.0,
    start_s: float = 0.0,
    work_offset_mm: float = 0.0,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Time the program from feeds and distances (seed 003 §1: the planned operation).

    A move takes ``|Δ| / feed · 60`` s (G0 at ``rapid_mm_min``, and no feed faster: the rapid is the
    machine's top speed), a G4 its dwell;
    nothing else takes time (no acceleration, tool changes, other axes' motion).
    The clock starts at ``start_s`` with the axis cold. The axis position is the
    program coordinate plus ``work_offset_mm`` (the machine coordinate the model
    knows).

    Returns ``(moves, process)``: ``moves`` one row per block of
    :attr:`Program.blocks` (``line, kind, compensate, start_mm, target_mm,
    axis_start_mm, axis_target_mm, feed_mm_min, dwell_s, t_start_s, t_end_s,
    duration_s``; feed 0 at a dwell), ``process`` the planned process log
    (``t_s, axis_mm, feed_mm_min``) every ``sample_s`` and at the program end,
    position linear within a move, feed of the move in force (0 at a dwell and
    after the end).
    """
    rapid = _check_positive("rapid_mm_min", rapid_mm_min)
    sample = _check_positive("sample_s", sample_s, upper=1.0)  # the dataset contract: >= 1 sample per second
    try:
        t = float(start_s)
        offset = float(work_offset_mm)
    except (TypeError, ValueError):
        raise PrecompError(
            f"start_s and work_offset_mm: expected numbers, got {start_s!r}, {work_offset_mm!r}"
        ) from None
    if not (math.isfinite(t) and math.isfinite(offset)):
        raise PrecompError(f"start_s and work_offset_mm: expected finite numbers, got {start_s!r}, {work_offset_mm!r}")
    if not any(b.compensate for b in program.blocks):
        raise PrecompError(f"{program.source}: no G0/G1 move on axis {program.axis}; nothing to compensate")
    start_s = t
    rows = []
    for b in program.blocks:
        if b.kind == "G4":
            feed, duration = 0.0, b.dwell_s
        else:  # no feed is faster than the machine's rapid (LinuxCNC limits it to the axis's maximum velocity)
            feed = rapid if b.feed_mm_min is None else min(b.feed_mm_min, rapid)
            duration = abs(b.target_mm - b.start_mm) / feed * 60.0
        rows.append(
            {
                "line": b.line,
                "kind": b.kind,
                "compensate": b.compensate,
                "start_mm": b.start_mm,
                "target_mm": b.target_mm,
                "axis_start_mm": b.start_mm + offset,
                "axis_target_mm": b.target_mm + offset,
                "feed_mm_min": feed,
                "dwell_s": b.dwell_s,
                "t_start_s": t,
                "t_end_s": t + duration,
                "duration_s": duration,
            }
        )
        t += duration
    moves = pd.DataFrame(rows)
    if t - start_s <= 0:
        raise PrecompError(
            f"{program.source}: the program takes no time on axis {program.axis} (all moves are zero-length)"
        )
    t_w, x_w, f_seg = _waypoints(moves, start_s)
    grid = np.arange(start_s, t, sample)
    if t - grid[-1] > 1e-6:
        grid = np.append(grid, t)
    axis_mm, feed_mm_min = _sample(t_w, x_w, f_seg, grid)
    process = pd.DataFrame({"t_s": grid, "axis_mm": axis_mm, "feed_mm_min": feed_mm_min})
    return moves, process


# --------------------------------------------------------------- prediction ---
def resolve_metadata(source) -> Metadata:
    """The dataset metadata a model was trained with (machine, screw, material, sensors):
    from a :class:`Dataset`, a :class:`Metadata`, a dataset directory or a benchmark
    dataset name (``seed000_x`` ...; built on first use)."""
    from ..data.io import DatasetError, load_metadata

    if isinstance(source, Dataset):
        return source.metadata
    if isinstance(source, Metadata):
        return source
    if isinstance(source, (str, Path)):
        path = Path(source)
        try:
            if path.is_dir():
                return load_metadata(path)
            from ..bench import datasets

            if str(source) in datasets.names():
                where = datasets.default_root() / str(source)
                if not datasets.is_built(str(source)):
                    # a simulation that writes a directory: said before it starts (minutes, in the working directory)
                    print(f"precompensate: the model's training dataset {source} is not at {where}; simulating it there "
                          "for its machine's metadata (--dataset DIR names one you have; THERMBENCH_DATA moves the "
                          "benchmark datasets)", file=sys.stderr, flush=True)  # fmt: skip
                built, _ = datasets.build(str(source))
                return load_metadata(built)
        except DatasetError as exc:
            raise PrecompError(f"dataset {source}: {exc}") from None
        from ..bench import datasets

        raise PrecompError(
            f"dataset {source!r}: not a dataset directory nor a benchmark dataset name; expected a directory "
            f"with metadata.yaml or one of {datasets.names()}"
        )
    raise PrecompError(
        f"dataset: expected a Dataset, Metadata, directory or benchmark name, got {type(source).__name__}"
    )


def _model_drive(model, metadata: Metadata) -> list[str]:
    """The ambient sensor(s) a model needs (held constant); an error when the model
    needs anything a planned program cannot supply (seed 003: no temperature sensors)."""
    if not isinstance(model, ThermalErrorModel):
        raise PrecompError(
            f"model: unsupported type {type(model).__module__}.{type(model).__name__}; expected a fitted thermbench "
            f"model that reads only the motion (PhysicsModel or AutoRegressiveSeed003)"
        )
    name = type(model).__name__
    try:
        inp = model.required_inputs()
    except ModelError as exc:
        raise PrecompError(f"model: {exc}") from None
    ambient = [s for s in inp.sensors if metadata.sensors.get(s) == "ambient"]
    if inp.ambient and not ambient and len(inp.sensors) == 1:
        ambient = list(inp.sensors)
    others = [s for s in inp.sensors if s not in ambient]
    if others:
        raise PrecompError(
            f"model: {name} needs temperature sensor(s) {others}, which a planned program cannot supply; expected "
            f"a model that reads only the motion (seed 003): physics (ambient held constant) or ar_seed003"
        )
    extra = [c for c in inp.operating if c not in MOTION_COLUMNS]
    if extra:
        raise PrecompError(
            f"model: {name} reads process column(s) {extra}; a planned program supplies only {list(MOTION_COLUMNS)}"
        )
    return ambient


def planned_dataset(
    metadata: Metadata,
    process: pd.DataFrame,
    ambient: dict[str, float] | None = None,
    run_id: str = RUN_ID,
    notes: str | None = None,
) -> Dataset:
    """A valid one-run :class:`Dataset` whose process log is the planned motion.

    The machine, screw and material are those of ``metadata`` (the training
    dataset's); the sensors are only ``ambient`` (name -> constant °C, a column
    ``<name>_C`` held at that value). The errors table holds one reading at the
    program start (error 0) so that the dataset meets the contract; the motion-driven
    models predict from the process log and the metadata only.
    """
    ambient = dict(ambient or {})
    pr = process[["t_s", "axis_mm", "feed_mm_min"]].astype(float).reset_index(drop=True)
    pr.insert(0, "run_id", run_id)
    for name, value in ambient.items():
        pr[f"{name}_C"] = float(value)
    lo, hi = float(pr["axis_mm"].min()), float(pr["axis_mm"].max())
    moving = pr.loc[pr["feed_mm_min"] > 0, "feed_mm_min"]
    meta = metadata.model_dump(mode="json", exclude_none=True)
    body = {
        "format": FORMAT,
        "machine": meta["machine"],
        "screw": meta["screw"],
        "material": meta["material"],
        "sensors": {s: metadata.sensors.get(s, "ambient") for s in ambient},
        "runs": {
            run_id: {
                "condition": {
                    "stroke_mm": hi - lo,
                    "start_mm": lo,
                    "end_mm": hi,
                    "feed_mm_min": float(moving.median()) if len(moving) else 0.0,
                },
                **({"notes": notes} if notes else {}),
            }
        },
    }
    errors = pd.DataFrame(
        {
            "run_id": [run_id],
            "t_s": [float(pr["t_s"].iloc[0])],
            "target_mm": [float(pr["axis_mm"].iloc[0])],
            "error_um": [0.0],
        }
    )
    return Dataset(Metadata.model_validate(body), pr, errors)


def predict_thermal_errors(
    model: ThermalErrorModel,
    metadata,
    process: pd.DataFrame,
    t_s,
    axis_mm,
    ambient_C: float = 20.0,
    notes: str | None = None,
) -> np.ndarray:
    """The model's thermal error (µm, measured - commanded) at (t, axis) pairs of the
    planned process log (:func:`planned_dataset` on the training dataset's
    ``metadata``), the ambient (if the model reads one) held at ``ambient_C``."""
    meta = resolve_metadata(metadata)
    ambient = _model_drive(model, meta)
    ds = planned_dataset(meta, process, {s: ambient_C for s in ambient}, notes=notes)
    try:
        e = model.predict_thermal_at(ds, RUN_ID, t_s, axis_mm)
    except ModelError as exc:
        raise PrecompError(f"model: {exc}") from None
    if not np.all(np.isfinite(e)):
        raise PrecompError(f"model: {type(model).__name__} predicted a non-finite error for the planned motion")
    return e