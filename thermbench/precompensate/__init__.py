"""Pre-compensation of a part program before machining (seed 003 §1).

Seed 003 compensates thermal errors "before machining" by revising the workpiece NC
program: the error is predicted "as soon as the workpiece NC machining program is
made", from the planned operation alone, with a model that needs no temperature
sensors. Here, for one feed axis:

1. :func:`parse_program` reads the G-code (G0/G1, G90/G91, F, G4 P<seconds>, G21,
   comments, N numbers, M codes); everything else passes through untouched and is
   listed with its line number and the reason;
2. :func:`plan_motion` times the program from feeds and distances and writes the
   planned process log (``t_s, axis_mm, feed_mm_min`` every ``sample_s``);
3. :func:`precompensate` predicts, with a fitted thermbench model that reads only
   the motion (:class:`~thermbench.models.physics.PhysicsModel`, the ambient held
   constant, or :class:`~thermbench.models.autoregressive.AutoRegressiveSeed003`),
   the thermal error each G0/G1 move meets at its end time at its target, and
   rewrites the target as ``target - error`` (incremental blocks get the increment
   that puts the axis on the compensated point);
4. :func:`verify_in_simulator` replays the original motion in the simulator
   (a :class:`~thermbench.sim.model.ScrewThermalModel` truth) and compares the
   error at every move end before and after.

:func:`run_precompensate` does it all from files; :func:`format_summary` prints it.
Every user mistake raises :class:`PrecompError` (a ``ValueError``) whose message
names the file, the line and what was expected. Full description:
docs/precompensate.md.

The package, one duty per module: :mod:`.program` (reading the G-code) → :mod:`.timing` (the
planned motion and the predicted errors) → :mod:`.revision` (the revised program and its check in
the simulator) → :mod:`.command` (from files, and the summary); :mod:`.axes` does it for every
axis of a program, each with its own model (``thermbench precompensate --axes``). The names below
are importable from the package itself, as before it was one module.
"""

from __future__ import annotations

from .program import Block, PrecompError, Program, ProgramError, Unsupported, parse_program
from .timing import plan_motion, planned_dataset, predict_thermal_errors, resolve_metadata
from .revision import PrecompResult, precompensate, simulate_true_errors, truth_from_metadata, verify_in_simulator
from .command import format_summary, run_precompensate

__all__ = [
    "Block",
    "PrecompError",
    "PrecompResult",
    "Program",
    "ProgramError",
    "Unsupported",
    "format_summary",
    "parse_program",
    "plan_motion",
    "planned_dataset",
    "precompensate",
    "predict_thermal_errors",
    "resolve_metadata",
    "run_precompensate",
    "simulate_true_errors",
    "truth_from_metadata",
    "verify_in_simulator",
]
