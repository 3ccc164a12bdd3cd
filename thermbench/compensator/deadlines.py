"""A control loop's schedule on absolute deadlines (no drift; after an overrun the missed
deadlines are skipped): the loops of ``thermbench compensator``, the station, and LinuxCNC's
component and plant."""

from __future__ import annotations


class Deadlines:
    """A loop's schedule on absolute deadlines ``start + k * period_s`` (no drift). After an
    overrun the missed deadlines are skipped (counted in :attr:`skipped`), not made up in a burst.
    ``max_cycles``/``duration_s``: when :meth:`next` says the loop is over (None: never)."""

    def __init__(self, period_s: float, start_s: float, max_cycles: int | None = None,
                 duration_s: float | None = None) -> None:  # fmt: skip
        self.period_s, self.start_s, self.k, self.skipped, self.cycles = period_s, start_s, 0, 0, 0
        self.max_cycles, self.duration_s = max_cycles, duration_s

    @property
    def deadline(self) -> float:
        return self.start_s + self.k * self.period_s

    def wait_s(self, now_s: float) -> float:
        return max(0.0, self.deadline - now_s)

    def next(self, end_s: float) -> str | None:
        """The cycle that began at :attr:`deadline` ended at ``end_s``: on to the next deadline;
        returns why the loop is over (``max_cycles``, ``duration_s``) or None."""
        late = end_s - self.deadline
        self.k += 1
        self.cycles += 1
        if late > self.period_s:
            missed = int((end_s - self.start_s) / self.period_s) - self.k + 1
            if missed > 0:
                self.skipped += missed
                self.k += missed
        if self.max_cycles is not None and self.cycles >= self.max_cycles:
            return "max_cycles"
        if self.duration_s is not None and end_s - self.start_s >= self.duration_s:
            return "duration_s"
        return None
