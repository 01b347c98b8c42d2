"""What a converter accepts as physically plausible: bounds on sizes, distances, angles and intrinsics.

A finite number is not yet a sensible one. A KITTI label with z = 1e30 or a calibration with
fx = 1e300 parses, and then yields keypoints at infinity, overflowing arithmetic or a record that
every consumer mis-reads. The bounds below are far outside anything a real road scene or camera
produces and far inside where float arithmetic goes wrong, so that a value beyond one is a typo or
a hostile file, never data. Each failure is a SourceError naming the file, the line or field, and
the bound (by its name here, so a user who does have such data knows what to change).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from omnigen.converters.common import SourceError

MIN_OBJECT_SIZE_M = 0.01
"""Smallest accepted box dimension (length, width or height), metres. The smallest labelled road
users (a child, a traffic cone) measure tens of centimetres; a box under 1 cm is an error, and a
vanishing one makes degenerate geometry (coincident corners, a zero-area silhouette)."""

MAX_OBJECT_SIZE_M = 50.0
"""Largest accepted box dimension, metres: longer than any road vehicle (an articulated bus or a
truck with trailers stays under 30 m). Beyond it, a number like 1e300 would overflow the corners."""

MAX_OBJECT_DISTANCE_M = 1000.0
"""Largest accepted coordinate of a box centre, metres from the sensor. Cameras of these datasets
resolve a car to a few pixels well inside a few hundred metres; 1000 m leaves room and keeps the
projection (and its squares) far from overflow."""

MAX_ABS_ANGLE_RAD = 4 * math.pi
"""Largest accepted |angle| (heading, observation angle). Datasets write angles in [-pi, pi] or
[0, 2 pi]; two full turns either way allow any convention, and beyond, sin and cos of a value like
1e30 are meaningless (its float spacing exceeds a turn)."""

MAX_PIXEL_COORDINATE = 100_000.0
"""Largest accepted |pixel coordinate| (2D boxes, principal point). omnigen.images caps an image
at 50 million pixels, so no side of a real image comes near; a box is allowed to overhang its image,
not to lie a hundred thousand pixels away."""

FOCAL_RANGE_PX = (10.0, 100_000.0)
"""Accepted focal lengths, pixels. A focal length of f pixels sees 2 atan(w / 2f) across an image w
pixels wide: 10 px over a 1000-pixel image is nearly 180 degrees (no pinhole camera), 100,000 px
over 2000 pixels is 1.1 degrees (no traffic camera); 1e300 is neither."""

MAX_SENSOR_OFFSET_M = 100.0
"""Largest accepted translation between two sensors of one rig (KITTI's camera 2 from camera 0,
DAIR-V2X's virtual LiDAR from the camera), metres. Rigs measure a few metres; an extrinsic of
kilometres is a unit error."""


def check_range(value: float, low: float, high: float, file: str | Path, where: str, what: str, bound: str) -> None:
    """A SourceError unless low <= value <= high (the bound's name is given for the message)."""
    if not low <= value <= high:
        raise SourceError(file, where, f"{what} {value:g} is outside [{low:g}, {high:g}] ({bound})")


def check_box(size: Sequence[float], center: Sequence[float], angle: float, file: str | Path, where: str,
              size_names: str = "l w h") -> None:
    """A 3D box's dimensions, centre and heading within the bounds above."""
    if min(size) < MIN_OBJECT_SIZE_M or max(size) > MAX_OBJECT_SIZE_M:
        raise SourceError(file, where, f"dimensions ({size_names}) {[float(v) for v in size]} must lie in "
                          f"[{MIN_OBJECT_SIZE_M:g}, {MAX_OBJECT_SIZE_M:g}] m (MIN_OBJECT_SIZE_M, MAX_OBJECT_SIZE_M)")
    if max(abs(v) for v in center) > MAX_OBJECT_DISTANCE_M:
        raise SourceError(file, where, f"location {[float(v) for v in center]} lies beyond "
                          f"{MAX_OBJECT_DISTANCE_M:g} m (MAX_OBJECT_DISTANCE_M)")
    check_angle(angle, file, where, "heading")


def check_angle(angle: float, file: str | Path, where: str, what: str) -> None:
    check_range(angle, -MAX_ABS_ANGLE_RAD, MAX_ABS_ANGLE_RAD, file, where, what, "MAX_ABS_ANGLE_RAD")


def check_box2d(box: Sequence[float], file: str | Path, where: str) -> None:
    if max(abs(v) for v in box) > MAX_PIXEL_COORDINATE:
        raise SourceError(file, where, f"2D box {[float(v) for v in box]} lies beyond {MAX_PIXEL_COORDINATE:g} px "
                          f"(MAX_PIXEL_COORDINATE)")


def check_intrinsics(K: np.ndarray, file: str | Path, where: str) -> None:
    """fx and fy within FOCAL_RANGE_PX, the skew and principal point within MAX_PIXEL_COORDINATE."""
    for value, what in ((K[0, 0], "fx"), (K[1, 1], "fy")):
        check_range(float(value), *FOCAL_RANGE_PX, file, where, f"focal length {what}", "FOCAL_RANGE_PX")
    for value, what in ((K[0, 1], "skew"), (K[0, 2], "cx"), (K[1, 2], "cy")):
        check_range(float(value), -MAX_PIXEL_COORDINATE, MAX_PIXEL_COORDINATE, file, where, what, "MAX_PIXEL_COORDINATE")


def check_offset(t: np.ndarray, file: str | Path, where: str, what: str) -> None:
    norm = float(np.linalg.norm(t))
    if not norm <= MAX_SENSOR_OFFSET_M:
        raise SourceError(file, where, f"{what} {np.asarray(t).tolist()} is {norm:g} m long, beyond "
                          f"{MAX_SENSOR_OFFSET_M:g} m (MAX_SENSOR_OFFSET_M)")
