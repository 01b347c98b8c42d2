"""A wall-clock budget for a training run (`omnigen train --time MINUTES`).

Why a plan and not a cut-off: the learning rate's warm-up and cosine decay, the keypoint sigma's
anneal and the last validation are laid out over the run's total number of iterations. A run
killed at its time limit stops at a high learning rate with a wide sigma, mid-schedule. Instead
the trainer measures how long an epoch (and a validation) takes, plans the number of epochs that
fit in what is left of the budget, gives that total to the schedule, and plans again at the end
of every epoch: the last planned epoch ends the cosine at lr0 * lrf.

Why the plan is made once an epoch, right after its training and before its validation: that one
decision says whether the epoch is the last, so the last is always validated and saved. A plan
made later (after the validation, or at the top of the next epoch) could find the budget spent by
the validation, the checkpoint's save or a slow disk, and end the run after an epoch that was
neither validated nor saved as the last. An epoch planned as the last stays the last: its
schedule has ended. The price is an overrun when the time after the decision is far longer than
measured (a validation or a save much slower than before): the run then ends at the next
decision, one epoch and a validation later.

The budget is the whole run's: a resumed run counts the seconds its earlier invocations trained
(results.csv's `time` column) and plans with what is left.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass, field

clock = time.perf_counter
"""The clock of a run's epoch times and budget; tests replace it to make the timing deterministic."""

VAL_SHARE = 0.1
"""Largest share of the training time that periodic validation may take in a time-boxed run: the
validation cadence is stretched (never shortened below --val-every) to keep under it."""


@dataclass
class TimeBudget:
    """Measured epoch and validation durations, and the plans made from them."""

    seconds: float  # the whole run's budget
    max_epochs: int  # --epochs: an upper bound
    epoch_seconds: list[float] = field(default_factory=list)  # training time of each measured epoch
    val_seconds: float | None = None  # the last validation's duration

    def __post_init__(self) -> None:
        if not 0 < self.seconds < math.inf:  # an infinite budget would overflow the plan's epoch count
            raise ValueError(f"TrainConfig.time_minutes: must be a finite number > 0, got {self.seconds / 60:g}")

    def epoch_estimate(self) -> float | None:
        """Seconds of training an epoch takes: the median of the last three measured, leaving out
        the first once there are others (it also pays for starting the loader processes and for
        the kernels' first calls and autotuning)."""
        measured = self.epoch_seconds[1:] or self.epoch_seconds
        return statistics.median(measured[-3:]) if measured else None

    def val_cadence(self, val_every: int) -> int:
        """Epochs between periodic validations: val_every, or more where a validation would take
        more than VAL_SHARE of the epochs between it and the previous one."""
        e = self.epoch_estimate()
        if self.val_seconds is None or not e:
            return val_every
        return max(val_every, math.ceil(self.val_seconds / (VAL_SHARE * e)))

    def plan(self, done: int, used: float, val_every: int, validates: bool) -> int:
        """The epoch the run should end at (exclusive), given `done` epochs and `used` seconds.

        Each further epoch costs its training time plus its share of the periodic validations;
        one validation is kept in reserve for the end. Before any epoch is measured the plan is
        max_epochs, the upper bound. While any time is left, one more epoch is planned even when
        less than a whole one fits: it is then the last, ends the schedule, and overruns the
        budget by less than an epoch (a run stopped instead would end mid-schedule). With no time
        left (the final validation counted) the plan is `done`: the epoch just trained is the last.
        """
        e = self.epoch_estimate()
        if e is None:
            return self.max_epochs
        v = (self.val_seconds or 0.0) if validates else 0.0
        cost = e + v / self.val_cadence(val_every)
        left = self.seconds - used - v
        if left <= 0:
            return done
        fit = max(1, math.floor(left / cost)) if cost > 0 else self.max_epochs
        return min(self.max_epochs, done + fit)
