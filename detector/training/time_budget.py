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

A run with a crop phase (the recipe's crop stage trained again apart, crop_train.crop_phase) keeps
CROP_SHARE of the budget for it: the detector's epochs are planned in the rest, and the crop
phase then trains the recipe's steps, or as many as fit in what is then left (`fit_steps`, a step
timed first; a phase that fits less than a tenth of its steps keeps the stage trained with the
detector). Why a share and not the detector first: the detector's plan would take every second, and
the crop stage trained apart is what places the published model's corners.
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


CROP_SHARE = 0.2
"""Share of a time-boxed run's budget kept for its crop phase. make validate's 7000 steps took 16.6
minutes in bf16 on 2 cores, under a fifth of its 125 minutes: its detector keeps the 100 minutes it
was validated with."""
MIN_CROP_SHARE_OF_STEPS = 0.1
"""A crop phase that fits fewer than this share of its steps is not trained: a stage trained that
briefly from scratch places corners worse than the one trained with the detector."""


def detector_seconds(minutes: float, crop_phase: bool) -> float:
    """The seconds of a --time budget of `minutes` the detector's epochs are planned in: all of it,
    or what the crop phase's share leaves."""
    seconds = minutes * 60
    return seconds - seconds * CROP_SHARE if crop_phase else seconds


def fit_steps(steps: int, step_seconds: float, left: float) -> int:
    """The crop phase's steps in `left` seconds at `step_seconds` a step: the recipe's `steps` where
    they fit, fewer where they do not, 0 where less than MIN_CROP_SHARE_OF_STEPS of them fit."""
    # the quotient rounded down, but not by float error (350 s at 0.1 s are 3500 steps, not 3499)
    fit = steps if step_seconds <= 0 else min(steps, math.floor(max(left, 0.0) / step_seconds + 1e-9))
    return fit if fit >= max(1, math.ceil(MIN_CROP_SHARE_OF_STEPS * steps)) else 0
