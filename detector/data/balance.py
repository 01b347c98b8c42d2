"""Class-balanced training: frames holding rare classes repeated, crops centred on rare objects.

Why: the evaluation's mAP is the mean of per-class APs, so a class of 24 training instances (trams in
make validate's data) weighs as much as one of 7263 (cars); in the run of 2026-11-26 trams scored
0.018 and the four other classes under 130 instances zero. Two standard remedies, both off by default:

- Repeat-factor sampling (Gupta et al., LVIS, 2019): a frame is drawn r = max(1, sqrt(t / f)) times
  an epoch, f being the fraction of training frames that hold its rarest class and t a threshold;
  frames with only common classes keep r = 1. The fractional part is drawn anew each epoch
  (train_loader.EpochBatches), so an epoch has a fixed number of frames.
- Focused crops: a training window of a quarter of the image area holds a given object only part
  of the time. With probability `crop_focus` the window is instead placed so that one object's
  centre lies in its middle half (where the zoom augmentation keeps it), the object drawn with
  weight 1 / (its class's instances in the training split): over the split each class is then
  chosen about as often as it occurs in frames, not as often as it has instances.
"""

from __future__ import annotations

import numpy as np


def check_crop_focus(crop_focus: float, crop: int | None) -> None:
    """A focus share is a probability and needs crop windows to place. One check for the dataset
    that draws the windows and for train's refusal before anything is loaded (and validate's,
    before anything is rendered)."""
    if not 0.0 <= crop_focus <= 1.0:  # False for NaN too
        raise ValueError(f"crop_focus: {crop_focus} is not a probability in [0, 1]")
    if crop_focus > 0 and crop is None:
        raise ValueError("crop_focus centres crop windows, but crop is not set (train --crop)")


def check_repeat_thresh(thresh: float) -> None:
    """A repeat-factor threshold is a finite number >= 0 (0: no frame repeated)."""
    if not np.isfinite(thresh) or thresh < 0:
        raise ValueError(f"repeat_thresh: {thresh} is not a finite number >= 0")


def frame_fractions(frame_classes: list[np.ndarray], num_classes: int) -> np.ndarray:
    """(num_classes,) fraction of the frames that hold at least one object of each class."""
    held = np.zeros(num_classes, dtype=np.float64)
    for cls in frame_classes:
        held[np.unique(cls)] += 1
    return held / max(1, len(frame_classes))


def repeat_factors(frame_classes: list[np.ndarray], num_classes: int, thresh: float) -> np.ndarray:
    """(frames,) LVIS repeat factor of each frame: max over its classes of max(1, sqrt(thresh / f_c)).

    A frame without objects is drawn once. `thresh` 0 repeats nothing."""
    check_repeat_thresh(thresh)
    f = frame_fractions(frame_classes, num_classes)
    with np.errstate(divide="ignore"):
        per_class = np.maximum(1.0, np.sqrt(thresh / np.where(f > 0, f, np.inf)))
    return np.array([per_class[np.unique(c)].max() if len(c) else 1.0 for c in frame_classes])


def instance_counts(frame_classes: list[np.ndarray], num_classes: int) -> np.ndarray:
    """(num_classes,) objects of each class over the frames."""
    counts = np.zeros(num_classes, dtype=np.int64)
    for cls in frame_classes:
        np.add.at(counts, cls, 1)
    return counts


def focus_weights(counts: np.ndarray) -> np.ndarray:
    """(num_classes,) weight of one object of each class when a crop picks the object it centres on:
    1 / the class's instances (0 for a class without any)."""
    return np.where(counts > 0, 1.0 / np.maximum(counts, 1), 0.0)


def pick_focus(cls: np.ndarray, weights: np.ndarray, rng: np.random.Generator) -> int | None:
    """Index of the object a focused crop centres on, drawn by its class's weight; None without
    objects (or with only weightless ones)."""
    if len(cls) == 0:
        return None
    w = weights[cls]
    total = float(w.sum())
    if total <= 0:
        return None
    return int(rng.choice(len(cls), p=w / total))


def focused_range(lo: float, hi: float, centre: float, window: int) -> tuple[float, float]:
    """The window origins in [lo, hi] that put `centre` in the middle half of the window; where
    none do (an object near the image's edge), the origin in [lo, hi] nearest to doing so."""
    a, b = centre - 0.75 * window, centre - 0.25 * window
    return min(max(a, lo), hi), max(min(b, hi), lo)


def epoch_frames(factors: np.ndarray) -> int:
    """Frames an epoch draws under repeat factors: each frame's whole repeats, and as many extra
    draws as the fractional parts add up to (rounded)."""
    whole = np.floor(factors)
    return int(whole.sum()) + int(round(float((factors - whole).sum())))


def describe(factors: np.ndarray) -> str:
    """One line for the training log: how many frames are repeated and how long an epoch is."""
    repeated = int((factors > 1).sum())
    return (f"repeat-factor sampling: {repeated} of {len(factors)} frames repeated (up to "
            f"{float(factors.max()):.2f}x), {epoch_frames(factors)} frames an epoch") if len(factors) else \
        "repeat-factor sampling: no frames"

