"""What omnigen accepts as physically plausible: bounds on sizes, distances, angles and pixel values.

A finite number is not yet a sensible one. A KITTI label with z = 1e30, a calibration with
fx = 1e300 or a hand-edited record with a corner at 1e308 parses, and then yields keypoints at
infinity, overflowing arithmetic or a dataset that every consumer mis-reads. The bounds below are
far outside anything a real road scene or camera produces and far inside where float arithmetic
goes wrong, so that a value beyond one is a typo or a hostile file, never data.

Two readers apply them: the converters (omnigen.converters.plausible, which turns a message here
into a skip naming the source file and line) and `omnigen validate` (record_problems: every record,
whoever wrote it: a render, a conversion, a merge or a text editor). Each message names the bound
by its name here, so a user who does have such data knows what to change. The core holds them so
that both layers share one set of numbers (the core imports no part).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Sequence

import numpy as np

from omnigen.conventions import NEAR_PLANE

if TYPE_CHECKING:
    from omnigen.record import FrameRecord, ObjectRecord

MIN_OBJECT_SIZE_M = 0.01
"""Smallest accepted box dimension (length, width or height), metres. The smallest labelled road
users (a child, a traffic cone) measure tens of centimetres; a box under 1 cm is an error, and a
vanishing one makes degenerate geometry (coincident corners, a zero-area silhouette)."""

MAX_OBJECT_SIZE_M = 50.0
"""Largest accepted box dimension, metres: longer than any road vehicle (an articulated bus or a
truck with trailers stays under 30 m). Beyond it, a number like 1e300 would overflow the corners."""

MAX_OBJECT_DISTANCE_M = 1000.0
"""Largest accepted coordinate of a box centre, metres from the sensor, and largest accepted
camera height above the ground plane. Cameras of these datasets resolve a car to a few pixels well
inside a few hundred metres, and the highest rig (a drone) flies about a hundred metres up; 1000 m
leaves room and keeps the projection (and its squares) far from overflow."""

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

MAX_KEYPOINT_COORDINATE = 1e10
"""Largest accepted |pixel coordinate| of a keypoint (a projected box corner), far looser than
MAX_PIXEL_COORDINATE on purpose. A corner of a real object that straddles the image plane lands far
outside the image: it is kept (null only behind NEAR_PLANE, 0.1 m), and u = fx x / z grows as z
shrinks. A 2000-pixel-focal camera beside a bus whose corner is 20 m to the side and 0.1 m ahead
puts that corner at 400,000 px, which MAX_PIXEL_COORDINATE would refuse; the fixtures and test
renders already reach 11,000 px on images 320 pixels wide. The bound is therefore the worst a
record within every other bound can produce, with room: a corner at most MAX_OBJECT_DISTANCE_M plus
half a MAX_OBJECT_SIZE_M box's diagonal (1043 m) to the side, NEAR_PLANE ahead, seen with the
largest focal length and principal point, lands at 1e5 * 1043 / 0.1 + 1e5, about 1.04e9 px. Ten
times that is 1e10, whose square (1e20) stays far inside float32 and float64; 1e308 is not data."""


MAX_WORLD_COORDINATE_M = 1e7
"""Largest accepted |coordinate| of a camera's position in its sequence's world frame
(camera_to_world's translation), metres. Not MAX_SENSOR_OFFSET_M: a world frame may be a map
projection (DAIR-V2X-C's is UTM-like, millions of metres east and north), which 1e7 m holds
(the Earth's circumference is 4e7 m), while 1e300 is not a place."""

MAX_SPEED_M_S = 70.0
"""Largest accepted |velocity|, m/s (252 km/h): above any road user in city traffic, whose
fastest (a car on an urban motorway) stays under half of it."""


def worst_keypoint_coordinate() -> float:
    """The farthest a keypoint can project for a record within the other bounds (see
    MAX_KEYPOINT_COORDINATE); a test keeps the bound above it if those change."""
    reach = MAX_OBJECT_DISTANCE_M + math.sqrt(3) * MAX_OBJECT_SIZE_M / 2
    return FOCAL_RANGE_PX[1] * reach / NEAR_PLANE + MAX_PIXEL_COORDINATE


# -- one value at a time: a message when out of bounds, None when plausible ----------------------

def range_problem(value: float, low: float, high: float, what: str, bound: str) -> str | None:
    """A message unless low <= value <= high (`bound` names the constant for the user)."""
    if not low <= value <= high:
        return f"{what} {value:g} is outside [{low:g}, {high:g}] ({bound})"
    return None


def size_problem(size: Sequence[float], size_names: str = "l w h") -> str | None:
    """A 3D box's dimensions within [MIN_OBJECT_SIZE_M, MAX_OBJECT_SIZE_M]."""
    if min(size) < MIN_OBJECT_SIZE_M or max(size) > MAX_OBJECT_SIZE_M:
        return (f"dimensions ({size_names}) {[float(v) for v in size]} must lie in "
                f"[{MIN_OBJECT_SIZE_M:g}, {MAX_OBJECT_SIZE_M:g}] m (MIN_OBJECT_SIZE_M, MAX_OBJECT_SIZE_M)")
    return None


def location_problem(center: Sequence[float]) -> str | None:
    """A 3D box's centre within MAX_OBJECT_DISTANCE_M of the sensor on every axis."""
    if max(abs(v) for v in center) > MAX_OBJECT_DISTANCE_M:
        return f"location {[float(v) for v in center]} lies beyond {MAX_OBJECT_DISTANCE_M:g} m (MAX_OBJECT_DISTANCE_M)"
    return None


def angle_problem(angle: float, what: str) -> str | None:
    return range_problem(angle, -MAX_ABS_ANGLE_RAD, MAX_ABS_ANGLE_RAD, what, "MAX_ABS_ANGLE_RAD")


def box2d_problem(box: Sequence[float]) -> str | None:
    if max(abs(v) for v in box) > MAX_PIXEL_COORDINATE:
        return f"2D box {[float(v) for v in box]} lies beyond {MAX_PIXEL_COORDINATE:g} px (MAX_PIXEL_COORDINATE)"
    return None


def intrinsics_problem(K: np.ndarray) -> str | None:
    """fx and fy within FOCAL_RANGE_PX, the skew and principal point within MAX_PIXEL_COORDINATE."""
    checks = [(K[0, 0], "focal length fx", FOCAL_RANGE_PX, "FOCAL_RANGE_PX"),
              (K[1, 1], "focal length fy", FOCAL_RANGE_PX, "FOCAL_RANGE_PX")]
    pixels = (-MAX_PIXEL_COORDINATE, MAX_PIXEL_COORDINATE)
    checks += [(K[0, 1], "skew", pixels, "MAX_PIXEL_COORDINATE"), (K[0, 2], "cx", pixels, "MAX_PIXEL_COORDINATE"),
               (K[1, 2], "cy", pixels, "MAX_PIXEL_COORDINATE")]
    for value, what, (low, high), bound in checks:
        if (message := range_problem(float(value), low, high, what, bound)) is not None:
            return message
    return None


def world_position_problem(t: np.ndarray) -> str | None:
    """A camera position (camera_to_world's translation) within MAX_WORLD_COORDINATE_M on every axis."""
    if np.abs(t).max() > MAX_WORLD_COORDINATE_M:
        return (f"camera position {np.asarray(t).tolist()} lies beyond {MAX_WORLD_COORDINATE_M:g} m "
                "(MAX_WORLD_COORDINATE_M)")
    return None


def speed_problem(velocity: np.ndarray) -> str | None:
    """A world velocity no faster than MAX_SPEED_M_S."""
    speed = float(np.linalg.norm(velocity))
    if speed > MAX_SPEED_M_S:
        return f"speed {speed:g} m/s of {np.asarray(velocity).tolist()} exceeds {MAX_SPEED_M_S:g} m/s (MAX_SPEED_M_S)"
    return None


def offset_problem(t: np.ndarray, what: str) -> str | None:
    norm = float(np.linalg.norm(t))
    if not norm <= MAX_SENSOR_OFFSET_M:
        return (f"{what} {np.asarray(t).tolist()} is {norm:g} m long, beyond "
                f"{MAX_SENSOR_OFFSET_M:g} m (MAX_SENSOR_OFFSET_M)")
    return None


# -- a whole record, as `omnigen validate` checks it ---------------------------------------------

def record_problems(rec: "FrameRecord") -> list[tuple[str, str]]:
    """(field, message) for every implausible value of a parsed record: K, the ground plane,
    camera height and camera_to_world's position, each object's box, keypoints, 2D boxes and world
    velocity, each ignore region.

    Objects are screened as stacked arrays (validate reads every record of a dataset) and only a
    suspect is checked field by field, where the message is written.
    """
    problems: list[tuple[str, str]] = []
    if (message := intrinsics_problem(np.asarray(rec.K))) is not None:
        problems.append(("K", message))
    height = (-MAX_OBJECT_DISTANCE_M, MAX_OBJECT_DISTANCE_M, "MAX_OBJECT_DISTANCE_M")
    if rec.ground_plane is not None:
        problems += _named("ground_plane.offset", range_problem(float(rec.ground_plane.offset), height[0], height[1],
                                                                "offset", height[2]))
    if rec.camera_height is not None:
        problems += _named("camera_height", range_problem(rec.camera_height, height[0], height[1], "height", height[2]))
    if rec.camera_to_world is not None:
        problems += _named("camera_to_world", world_position_problem(np.asarray(rec.camera_to_world)[:3, 3]))
    for i in _suspect_objects(rec.objects):
        problems += _object_problems(rec.objects[i], f"objects[{i}]")
    for i, region in enumerate(rec.ignore_regions):
        problems += _named(f"ignore_regions[{i}].bbox", box2d_problem(region.bbox))
    return problems


def _named(field: str, message: str | None) -> list[tuple[str, str]]:
    return [] if message is None else [(field, message)]


def _suspect_objects(objects: "list[ObjectRecord]") -> np.ndarray:
    """Indices of objects with any value beyond a bound, from a few whole-frame array operations."""
    if not objects:
        return np.zeros(0, dtype=np.int64)
    dims = np.array([o.box.dims for o in objects])
    centers = np.array([o.box.center for o in objects])
    keypoints = np.nan_to_num(np.array([o.keypoints for o in objects]), nan=0.0).reshape(len(objects), -1)
    boxes = np.array([np.concatenate([o.bbox, _or_zeros(o.bbox_source), _or_zeros(o.bbox_visible)])
                      for o in objects])
    speeds = np.linalg.norm([_or_zeros(o.velocity, 3) for o in objects], axis=1)
    suspect = ((dims.min(axis=1) < MIN_OBJECT_SIZE_M) | (dims.max(axis=1) > MAX_OBJECT_SIZE_M)
               | (np.abs(centers).max(axis=1) > MAX_OBJECT_DISTANCE_M)
               | (np.abs(keypoints).max(axis=1) > MAX_KEYPOINT_COORDINATE)
               | (np.abs(boxes).max(axis=1) > MAX_PIXEL_COORDINATE) | (speeds > MAX_SPEED_M_S))
    return np.flatnonzero(suspect)


def _or_zeros(values: np.ndarray | None, size: int = 4) -> np.ndarray:
    return np.zeros(size) if values is None else np.asarray(values, dtype=np.float64)


def _object_problems(o: "ObjectRecord", path: str) -> list[tuple[str, str]]:
    problems = _named(f"{path}.box3d.dims", size_problem(o.box.dims))
    problems += _named(f"{path}.box3d.center", location_problem(o.box.center))
    for j, (u, v) in enumerate(np.asarray(o.keypoints, dtype=np.float64)):
        if max(abs(u), abs(v)) > MAX_KEYPOINT_COORDINATE:  # NaN (behind the camera) compares False
            problems.append((f"{path}.keypoints[{j}]", f"[{u:g}, {v:g}] lies beyond {MAX_KEYPOINT_COORDINATE:g} px "
                                                       "(MAX_KEYPOINT_COORDINATE)"))
    for name in ("bbox", "bbox_source", "bbox_visible"):
        box = getattr(o, name)
        if box is not None:
            problems += _named(f"{path}.{name}", box2d_problem(box))
    if o.velocity is not None:
        problems += _named(f"{path}.velocity", speed_problem(o.velocity))
    return problems
