"""A run length in steps that also respects a wall-clock budget: the CPU is shared, so the
number of steps that fit is re-estimated from the measured step rate as training goes, and
learning-rate schedules follow the fraction of the (current) total."""

from __future__ import annotations

import time


class StepBudget:
    def __init__(self, max_steps: int, seconds: float = 0.0, min_steps: int = 1):
        self.max_steps = max(1, max_steps)
        self.seconds = seconds
        self.min_steps = min_steps
        self.total = self.max_steps
        self.t0 = time.time()

    def update(self, step: int) -> int:
        """Call after `step` steps are done; returns the current total."""
        if self.seconds > 0 and step > 0 and (step in (3, 10, 30) or step % 50 == 0):
            rate = (time.time() - self.t0) / step
            fit = int(self.seconds / rate)
            self.total = max(self.min_steps, step + 1, min(self.max_steps, fit))
        return self.total

    def progress(self, step: int) -> float:
        return min(1.0, step / self.total)
