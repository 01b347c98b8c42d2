"""Size priors per fine class: what a plausible object of each class measures (l, w, h in metres).

Why a module of its own: the statistics report compares every dataset against these numbers and
its health check flags objects far outside them; a converter or a detector's anchor sizes may
want the same reference. Scene generators may draw from their own, richer distributions; these
priors are a yardstick, not a generator.

Each class has a mean and a spread (one standard deviation) per dimension. The means are typical
road-user sizes (KITTI and DAIR-V2X label averages, rounded; street furniture from common
standards); the spreads are wide enough to hold the real variety of a class (a city car and an
estate car, a child and an adult). An object is "far outside" its prior when any dimension lies
more than `FAR_SIGMA` spreads from the mean: with a normal spread that is rarer than 1 in 15,000
per dimension, so a flag almost always means a mislabelled class or swapped dimensions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnigen.conventions import FINE_CLASSES

FAR_SIGMA = 4.0
"""Spreads from the mean beyond which a dimension counts as far outside its class prior."""


@dataclass(frozen=True)
class SizePrior:
    """Mean and spread (1 sigma) of [l, w, h] in metres for one class."""

    mean: tuple[float, float, float]
    std: tuple[float, float, float]


PRIORS: dict[str, SizePrior] = {
    "car": SizePrior((4.2, 1.8, 1.5), (0.45, 0.12, 0.15)),
    "van": SizePrior((5.0, 2.0, 2.1), (0.6, 0.15, 0.25)),
    "truck": SizePrior((8.0, 2.5, 3.2), (2.5, 0.25, 0.5)),
    "bus": SizePrior((11.0, 2.6, 3.2), (1.5, 0.15, 0.35)),
    "tram": SizePrior((25.0, 2.6, 3.4), (6.0, 0.2, 0.3)),
    "pedestrian": SizePrior((0.6, 0.6, 1.75), (0.2, 0.15, 0.15)),
    "cyclist": SizePrior((1.8, 0.6, 1.7), (0.25, 0.15, 0.15)),
    "motorcyclist": SizePrior((2.0, 0.8, 1.6), (0.3, 0.2, 0.2)),
    "tricyclist": SizePrior((2.6, 1.2, 1.7), (0.4, 0.25, 0.25)),
    "barrow": SizePrior((1.2, 0.6, 1.0), (0.3, 0.2, 0.2)),
    "traffic_cone": SizePrior((0.4, 0.4, 0.7), (0.1, 0.1, 0.15)),
    "misc": SizePrior((2.0, 1.5, 1.5), (1.5, 0.8, 0.8)),
}
assert set(PRIORS) == set(FINE_CLASSES), "every fine class needs a size prior"

PRIOR_MEAN = np.array([PRIORS[c].mean for c in FINE_CLASSES], dtype=np.float64)
"""(classes, 3) prior means in FINE_CLASSES order, for indexing by an object table's category."""
PRIOR_STD = np.array([PRIORS[c].std for c in FINE_CLASSES], dtype=np.float64)
"""(classes, 3) prior spreads in FINE_CLASSES order."""


def dims_z_scores(category: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """(N, 3) signed distance of each object's [l, w, h] from its class mean, in spreads."""
    category = np.asarray(category, dtype=np.int64)
    return (np.asarray(dims, dtype=np.float64) - PRIOR_MEAN[category]) / PRIOR_STD[category]


def far_outside_prior(category: np.ndarray, dims: np.ndarray, sigma: float = FAR_SIGMA) -> np.ndarray:
    """(N,) True where any dimension lies more than `sigma` spreads from its class mean."""
    return (np.abs(dims_z_scores(category, dims)) > sigma).any(axis=1)
