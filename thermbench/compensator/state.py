"""The compensator's runtime state on disk, for warm restarts.

The C runtime keeps a model's state in its arena, with pointers into it: its bytes do not
survive the process. What does is what made the state: the samples the model was stepped
with since its last start. :class:`StateStore` keeps them in ``<state>.samples.csv`` (one row
per stepped sample, appended as they come) and the rest of the state in ``<state>`` (JSON:
machine-time origin and last timestamp, grid index, the compensation the controller holds,
how many sample rows are valid), written atomically every ``state.every_s``. A restarted
compensator reads both, and :meth:`thermbench.compensator.control.CycleLogic.resume_decision`
says whether to re-step them (a day at 1 Hz is 86 400 steps of the C runtime: well under a
second) or to start cold.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np

from ..outputs import OutputStream, check_output_file, write_text


class StateError(ValueError):
    """A state file that cannot be read (names it)."""


class StateStore:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.samples_path = self.path.with_name(self.path.name + ".samples.csv")
        check_output_file(self.path, "compensator-state")  # never over a file thermbench did not write
        check_output_file(self.samples_path, "compensator-state-samples")
        self.out: OutputStream | None = None
        self.n = 0
        self.generation = -1

    def load(self) -> tuple[dict, np.ndarray] | None:
        """The saved state and its valid sample rows; None when there is none."""
        if not self.path.exists():
            return None
        try:
            header = json.loads(self.path.read_text())
            n = int(header["rows"])
            rows = np.zeros((0, 0))
            if n and self.samples_path.exists() and self.samples_path.stat().st_size:
                rows = np.loadtxt(self.samples_path, delimiter=",", ndmin=2, max_rows=n)
            if len(rows) != n or (n and int(rows[-1][0]) != int(header.get("k_last", -1))):
                # cut short by a crash between the samples and the state (or a restart's new samples):
                # not this state's samples, so not usable; a loud cold start, not a refusal
                header["_problem"] = (f"the saved state is inconsistent ({self.samples_path.name} has {len(rows)} rows "
                                      f"ending at grid point {int(rows[-1][0]) if len(rows) else None}; the state says {n}, "
                                      f"ending at {header.get('k_last')})")  # fmt: skip
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise StateError(f"config key 'state.path': {self.path}: not a compensator state ({exc}); move it away to start "
                             "cold") from None  # fmt: skip
        return header, rows

    def sync(self, stepped: list, generation: int) -> None:
        """Append the rows of ``stepped`` not written yet (all of them after a model restart)."""
        if self.out is None or generation != self.generation or len(stepped) < self.n:
            if self.out is not None:
                self.out.close()
            self.out = OutputStream(self.samples_path, "compensator-state-samples")
            self.writer = csv.writer(self.out.fh)
            self.n, self.generation = 0, generation
        for row in stepped[self.n :]:
            self.writer.writerow([repr(float(v)) for v in row])
        self.n = len(stepped)

    def save(self, header: dict) -> None:
        """The state, after its samples are on disk (flushed and fsynced: a power cut leaves the
        state behind its samples, never ahead)."""
        if self.out is not None:
            self.out.fh.flush()
            os.fsync(self.out.fh.fileno())
        write_text(self.path, json.dumps({**header, "rows": self.n}, indent=2) + "\n", "compensator-state")

    def close(self) -> None:
        if self.out is not None:
            self.out.close()
