"""What a converter accepts as physically plausible: the core's bounds (omnigen.plausible), raised
as a SourceError naming the source file and its line or field.

The bounds and their reasons live in the core, which `omnigen validate` applies to every record of
a dataset whoever wrote it; this module keeps the converters' names and turns each message into
the skip a converter reports (e.g. `line 1: location [...] lies beyond 1000 m (MAX_OBJECT_DISTANCE_M)`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from omnigen.converters.common import SourceError
from omnigen.plausible import (  # noqa: F401  (re-exported: the converters' names for the bounds)
    FOCAL_RANGE_PX,
    MAX_ABS_ANGLE_RAD,
    MAX_OBJECT_DISTANCE_M,
    MAX_OBJECT_SIZE_M,
    MAX_PIXEL_COORDINATE,
    MAX_SENSOR_OFFSET_M,
    MIN_OBJECT_SIZE_M,
    angle_problem,
    box2d_problem,
    intrinsics_problem,
    location_problem,
    offset_problem,
    range_problem,
    size_problem,
)


def _refuse(message: str | None, file: str | Path, where: str) -> None:
    if message is not None:
        raise SourceError(file, where, message)


def check_range(value: float, low: float, high: float, file: str | Path, where: str, what: str, bound: str) -> None:
    """A SourceError unless low <= value <= high (the bound's name is given for the message)."""
    _refuse(range_problem(value, low, high, what, bound), file, where)


def check_box(size: Sequence[float], center: Sequence[float], angle: float, file: str | Path, where: str,
              size_names: str = "l w h") -> None:
    """A 3D box's dimensions, centre and heading within the bounds."""
    _refuse(size_problem(size, size_names), file, where)
    _refuse(location_problem(center), file, where)
    check_angle(angle, file, where, "heading")


def check_angle(angle: float, file: str | Path, where: str, what: str) -> None:
    _refuse(angle_problem(angle, what), file, where)


def check_box2d(box: Sequence[float], file: str | Path, where: str) -> None:
    _refuse(box2d_problem(box), file, where)


def check_intrinsics(K: np.ndarray, file: str | Path, where: str) -> None:
    """fx and fy within FOCAL_RANGE_PX, the skew and principal point within MAX_PIXEL_COORDINATE."""
    _refuse(intrinsics_problem(K), file, where)


def check_offset(t: np.ndarray, file: str | Path, where: str, what: str) -> None:
    _refuse(offset_problem(t, what), file, where)
