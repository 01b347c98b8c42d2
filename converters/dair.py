"""DAIR-V2X-I and the infrastructure side of DAIR-V2X-C (pitched pole cameras) into UrbanOmniView.

Usage: `omnigen convert dair SRC --out DIR`, where SRC is a DAIR-V2X-I folder
(`single-infrastructure-side`), a DAIR-V2X-C `infrastructure-side` folder, or the DAIR-V2X-C root
that holds `infrastructure-side/`. A root with `cooperative/data_info.json` also gives the vehicle
side, paired and posed in the world (omnigen.converters.dair_cooperative; --side picks the sides). docs/converters-dair.md explains every decision; the short
version of the ones that change numbers:

- Boxes are built in the virtual-LiDAR frame (x forward, y left, z up; `3d_location` is the box
  centre, `rotation` the yaw about +z, 0 along +x, `l` along the heading) and carried into the
  camera with `virtuallidar_to_camera` (omnigen.formats.dair.box_from_dair). The camera's pitch is
  therefore part of every box's rotation, and top and bottom come from the LiDAR's z. The official
  DAIR-to-KITTI converter is not used: it writes headings 90 degrees off and drops the pitch.
- Keypoints come from `label/camera` (boxes fitted to the image); `label/virtuallidar` (fitted to
  the point cloud, at the point cloud's time) is used only when asked (--label virtuallidar, or
  --fallback-virtuallidar for frames whose camera label is missing).
- Classes are compared case-insensitively with conventions.DAIR_CLASSES; every other class
  (DAIR's ignore and unknown classes, and any name we do not know) becomes an ignore region with the
  label's 2D box, so that a detector is neither rewarded nor punished there.
- The ground plane is fitted through the boxes' bottom corners in the virtual-LiDAR frame when a
  frame has enough objects, else it is the level plane at their median bottom height; it is then
  carried into the camera, and camera height and pitch are read off it.
"""

from __future__ import annotations

import argparse
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import orjson

from omnigen.converters.common import (
    TEXT_FILE_MAX_BYTES,
    ConvertedFrame,
    ImageSource,
    SourceError,
    add_common_arguments,
    image_relpath,
    print_report,
    read_source_bytes,
    run_conversion,
    select_keys,
    source_image_size,
    source_path,
)
from omnigen.converters.plausible import check_box, check_box2d, check_intrinsics, check_offset
from omnigen.conventions import BOTTOM_CORNERS, DAIR_CLASSES, OCCLUSION_UNKNOWN
from omnigen.formats.dair import box_from_dair, boxes_from_dair
from omnigen.geometry import (
    Box3D,
    Plane,
    cuboid_corners,
    fit_ground,
    project_boxes,
    rots_z,
    self_occluded_corners_batch,
)
from omnigen.options import number
from omnigen.record import FRAME_ID_PATTERN, FrameRecord, IgnoreRegion, ObjectRecord

# ---------------------------------------------------------------------------------------------
# The format, as the official repository writes it (AIR-THU/DAIR-V2X: data/README.md, v2x/dataset)
# ---------------------------------------------------------------------------------------------

SOURCE_I = "dair-v2x-i"
SOURCE_C = "dair-v2x-c"
VIEW = "infrastructure"
DATA_INFO = "data_info.json"
INFRASTRUCTURE_SIDE = "infrastructure-side"

LABEL_SETS = ("camera", "virtuallidar")
LABEL_KEYS: dict[str, tuple[str, ...]] = {
    # the official code reads the *_std_path keys; the README writes the others
    "camera": ("label_camera_std_path", "label_camera_path"),
    "virtuallidar": ("label_lidar_std_path", "label_lidar_path", "label_virtuallidar_path"),
}
LABEL_DIRS: dict[str, tuple[str, ...]] = {"camera": ("label/camera",), "virtuallidar": ("label/virtuallidar",)}
INTRINSIC_KEYS = ("calib_camera_intrinsic_path",)
INTRINSIC_DIRS = ("calib/camera_intrinsic", "calib/camera")  # the README's DAIR-V2X-C tree says calib/camera
EXTRINSIC_KEYS = ("calib_virtuallidar_to_camera_path",)
EXTRINSIC_DIRS = ("calib/virtuallidar_to_camera",)
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")



@dataclass(frozen=True)
class DairSide:
    """Where one camera's files are named: its view, frame-id tag, label and extrinsic keys and folders.

    Why: DAIR-V2X-C's vehicle side has the infrastructure side's layout with other names
    (label/lidar, calib/lidar_to_camera); one converter serves both with the names passed in.
    """

    view: str
    tag: str  # between the source and the DAIR id in frame ids: "" (infrastructure) or "veh-"
    label_keys: dict[str, tuple[str, ...]]
    label_dirs: dict[str, tuple[str, ...]]
    extrinsic_keys: tuple[str, ...]
    extrinsic_dirs: tuple[str, ...]


INFRASTRUCTURE = DairSide(VIEW, "", LABEL_KEYS, LABEL_DIRS, EXTRINSIC_KEYS, EXTRINSIC_DIRS)
VEHICLE = DairSide(
    "ego", "veh-",
    # on the vehicle side "virtuallidar" names the point-cloud label set, label/lidar
    {"camera": LABEL_KEYS["camera"], "virtuallidar": ("label_lidar_std_path", "label_lidar_path")},
    {"camera": ("label/camera",), "virtuallidar": ("label/lidar",)},
    ("calib_lidar_to_camera_path",), ("calib/lidar_to_camera",))

C_MARKERS = ("batch_id", "batch_start_id", "batch_end_id", "valid_batch_splits", "calib_virtuallidar_to_world_path")
"""data_info fields only DAIR-V2X-C's infrastructure side carries; any of them means `dair-v2x-c`."""

GEOMETRY_KEYS = ("2d_box", "3d_dimensions", "3d_location", "rotation")
"""Label fields that become record fields; every other field goes to source_attributes untouched."""

TIMESTAMP_KEYS = ("image_timestamp", "pointcloud_timestamp")  # microseconds, as digit strings

DATA_INFO_MAX_BYTES = 512 * 2**20
"""Largest data_info.json read. It holds one entry of about a kilobyte per frame, so this allows
hundreds of thousands of frames (DAIR-V2X-C's infrastructure side has 12,424) and refuses a file
(or a link to /dev/zero) that would fill memory. Label and calibration files have the smaller
omnigen.converters.common.TEXT_FILE_MAX_BYTES."""

# ---------------------------------------------------------------------------------------------
# Decisions (docs/converters-dair.md)
# ---------------------------------------------------------------------------------------------

DEFAULT_GROUP_GAP_S = 10.0
"""Two frames of one camera whose timestamps differ by at most this many seconds are neighbours and
share a group. 10 s keeps a red-light queue (the same cars, seen again and again) on one side of a
split, yet separates recordings minutes apart."""
GROUP_GAP_RANGE_S = (0.0, 86400.0)
"""--group-gap accepts 0 (only equal timestamps share a run) to a day (in practice one run per
intersection); a negative gap gave every frame its own run, NaN or infinity one run for all."""

GROUP_METHODS = ("batch", "time", "intersection")

PLANE_MIN_OBJECTS = 5
"""Fit a tilted ground plane only through the bottoms of at least this many objects; fewer leave the
tilt poorly determined, and a level plane (the virtual LiDAR's z is up) is the better guess."""

PLANE_MAX_TILT_DEG = 6.0
"""A fitted plane tilted more than this from the LiDAR's level is rejected (a 10% grade is 5.7
degrees): such a fit comes from boxes on kerbs and ramps, not from the road."""

LIDAR_UP = np.array([0.0, 0.0, 1.0])
"""The virtual LiDAR's z is up: the level ground's normal, and the side a fitted normal points to."""

ROTATION_TOLERANCE = 0.05
"""Largest |R^T R - I| entry accepted in an extrinsic rotation. Calibrated matrices are orthonormal
only to a few decimals; within this tolerance R is replaced by the nearest rotation (SVD), so that
every stored box rotation is a proper rotation. Beyond it the file is rejected as not a rotation."""

ORTHONORMAL_EPS = 1e-9
"""Below this deviation R is used exactly as given (byte-identical to the source)."""


# ---------------------------------------------------------------------------------------------
# Reading values that may be numbers or strings
# ---------------------------------------------------------------------------------------------


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def read_json(path: Path, named_by: str = "", max_bytes: int = TEXT_FILE_MAX_BYTES) -> Any:
    """Parse a JSON file; a missing, broken or oversized file is a SourceError naming it (and who named it).

    The file must be a regular file of at most max_bytes (omnigen.converters.common.read_source_bytes),
    checked before it is opened. Nesting deeper than the parsers allow (orjson stops at 1024
    levels, json at Python's recursion limit) is a SourceError too, not a RecursionError that
    would stop the whole run.

    orjson parses first (several times faster; three files a frame). It rejects what json accepts
    in a few corners (NaN, UTF-16 files, lone surrogates, 1e400); those files go through json,
    which then answers or names the error exactly as before. One difference remains: orjson
    reads integers beyond 64 bits as floats, which json would keep as ints that the record writer
    (orjson too) cannot encode.
    """
    try:
        data = read_source_bytes(path, max_bytes, named_by)
    except FileNotFoundError:
        raise SourceError(path, "", f"missing{f' ({named_by})' if named_by else ''}") from None
    try:
        return orjson.loads(data)
    except orjson.JSONDecodeError:
        pass  # json below gives the same answer where orjson is stricter, or names the error as before
    try:
        return json.loads(data, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise SourceError(path, f"line {exc.lineno} column {exc.colno}", f"not valid JSON: {exc.msg}") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise SourceError(path, "", f"not valid JSON: {exc}") from None
    except RecursionError:
        raise SourceError(path, "", "JSON nested too deeply to read") from None


def _reject_constant(name: str) -> float:
    # NaN and Infinity are not JSON; Python would accept them and the record writer would then fail.
    raise ValueError(f"{name} is not a JSON number")


def as_number(value: Any, file: Path, where: str) -> float:
    """A finite number given as a JSON number or as a string ("0", "1.5"), as DAIR-V2X writes both."""
    if type(value) is float and math.isfinite(value):  # the common case first: ~11 numbers an object
        return value
    if isinstance(value, bool):
        number = math.nan
    elif isinstance(value, (int, float)):
        number = float(value)
    elif isinstance(value, str):
        try:
            number = float(value.strip())
        except ValueError:
            raise SourceError(file, where, f"expected a number, got {_short(value)}") from None
    else:
        raise SourceError(file, where, "missing" if value is None else f"expected a number, got {_short(value)}")
    if not math.isfinite(number):
        raise SourceError(file, where, f"expected a finite number, got {_short(value)}")
    return number


def as_matrix(value: Any, shape: tuple[int, ...], file: Path, where: str) -> np.ndarray:
    """Numbers (or numeric strings) of the given shape, nested or flat row-major (3x1 == 3)."""
    if value is None:
        raise SourceError(file, where, "missing")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise SourceError(file, where, f"expected {'x'.join(map(str, shape))} numbers, got {_short(value)}") from None
    if arr.size != math.prod(shape) or arr.ndim == 0:
        raise SourceError(file, where, f"expected {'x'.join(map(str, shape))} numbers, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise SourceError(file, where, "contains NaN or infinity")
    return arr.reshape(shape)


# ---------------------------------------------------------------------------------------------
# Calibration
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Extrinsics:
    """Virtual LiDAR to camera: X_cam = calibrated @ X_lidar + translation.

    Points (box centres, a point of the ground plane) go through the matrix as calibrated, as the
    dataset's own tools map them; directions that must stay a proper rotation (a box's axes, the
    plane's normal) go through `rotation`, its nearest rotation. The two differ only as much as
    the calibration is not orthonormal (ROTATION_TOLERANCE at most).
    """

    rotation: np.ndarray
    translation: np.ndarray
    calibrated: np.ndarray

    def up_in_camera(self) -> np.ndarray:
        """The virtual LiDAR's +z (up) seen from the camera."""
        return self.rotation[:, 2]


def parse_intrinsics(data: Any, file: Path) -> np.ndarray:
    """K from `cam_K` (row-major, flat 9 or 3x3). `cam_D` is ignored, as the official code does."""
    if not isinstance(data, dict):
        raise SourceError(file, "", f"expected a JSON object with cam_K, got {type(data).__name__}")
    K = as_matrix(data.get("cam_K"), (3, 3), file, "cam_K")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - (0.0, 0.0, 1.0)).max() > 1e-6:
        raise SourceError(file, "cam_K", f"not a pinhole intrinsic matrix: {K.tolist()}")
    check_intrinsics(K, file, "cam_K")
    return K


def parse_extrinsics(data: Any, file: Path) -> Extrinsics:
    """`{"rotation": 3x3, "translation": 3x1}`, or `Tr_velo_to_cam` (3x4 or 4x4, nested or flat).

    Some tools wrap the pair in `{"transform": {...}}` (as the vehicle side's lidar_to_novatel
    does); that is accepted too.
    """
    if isinstance(data, dict) and isinstance(data.get("transform"), dict):
        data = data["transform"]
    if not isinstance(data, dict):
        raise SourceError(file, "", f"expected a JSON object with rotation and translation, got {type(data).__name__}")
    if "rotation" in data or "translation" in data:
        rotation = as_matrix(data.get("rotation"), (3, 3), file, "rotation")
        translation = as_matrix(data.get("translation"), (3,), file, "translation")
        rotation_field = "rotation"
    elif "Tr_velo_to_cam" in data:
        rotation, translation = _split_transform(data["Tr_velo_to_cam"], file)
        rotation_field = "Tr_velo_to_cam"
    else:
        raise SourceError(file, "rotation", "missing: expected rotation and translation, or Tr_velo_to_cam")
    check_offset(translation, file, "translation" if rotation_field == "rotation" else rotation_field, "translation")
    return Extrinsics(nearest_rotation(rotation, file, rotation_field), translation, rotation)


def _split_transform(value: Any, file: Path) -> tuple[np.ndarray, np.ndarray]:
    """[R | t] from a 3x4 or 4x4 matrix (the 4x4 must end in 0 0 0 1)."""
    try:
        size = np.asarray(value, dtype=np.float64).size
    except (TypeError, ValueError):
        size = 0  # as_matrix below names the problem
    if size == 16:
        m = as_matrix(value, (4, 4), file, "Tr_velo_to_cam")
        if np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-6:
            raise SourceError(file, "Tr_velo_to_cam", f"last row of a 4x4 transform must be 0 0 0 1, got {m[3].tolist()}")
    else:
        m = as_matrix(value, (3, 4), file, "Tr_velo_to_cam")
    return m[:3, :3].copy(), m[:3, 3].copy()


def nearest_rotation(r: np.ndarray, file: Path, where: str) -> np.ndarray:
    """r itself when orthonormal, its nearest rotation when nearly so, else a SourceError."""
    deviation = float(np.abs(r.T @ r - np.eye(3)).max())
    if deviation > ROTATION_TOLERANCE or np.linalg.det(r) <= 0:
        raise SourceError(file, where, f"not a rotation matrix (|R^T R - I| = {deviation:.3g}, det = {np.linalg.det(r):.3g})")
    if deviation <= ORTHONORMAL_EPS:
        return r
    u, _, vt = np.linalg.svd(r)
    return u @ vt


# ---------------------------------------------------------------------------------------------
# Labels
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LabelObject:
    """One labelled object of a known class, still in the virtual-LiDAR frame."""

    index: int  # position in the label file; instance_id = index + 1, so a record points back at it
    category: str
    center: np.ndarray  # (3,) box centre
    lwh: np.ndarray  # (3,) l, w, h
    yaw: float
    box2d: np.ndarray  # (4,) the label's 2d_box
    occlusion_level: int
    attributes: dict[str, Any]


@dataclass
class ParsedLabel:
    objects: list[LabelObject] = field(default_factory=list)
    ignore_regions: list[IgnoreRegion] = field(default_factory=list)


def parse_label(data: Any, file: Path) -> ParsedLabel:
    """A DAIR-V2X label file (a list of objects) into known-class objects and ignore regions."""
    if not isinstance(data, list):
        raise SourceError(file, "", f"expected a JSON list of objects, got {type(data).__name__}")
    parsed = ParsedLabel()
    for i, obj in enumerate(data):
        item = parse_label_object(obj, file, i)
        if isinstance(item, IgnoreRegion):
            parsed.ignore_regions.append(item)
        else:
            parsed.objects.append(item)
    return parsed


def parse_label_object(obj: Any, file: Path, i: int) -> LabelObject | IgnoreRegion:
    """One label entry; a class outside DAIR_CLASSES becomes an ignore region with its 2D box."""
    at = f"[{i}]"
    if not isinstance(obj, dict):
        raise SourceError(file, at, f"expected a JSON object, got {type(obj).__name__}")
    name = obj.get("type")
    if not isinstance(name, str) or not name.strip():
        raise SourceError(file, f"{at}.type", f"expected a class name, got {_short(name)}")
    box2d = parse_box2d(obj.get("2d_box"), file, f"{at}.2d_box")
    category = DAIR_CLASSES.get(name.strip().lower())
    if category is None:
        return IgnoreRegion(box2d, name)
    dims = _numbers(obj, "3d_dimensions", ("l", "w", "h"), file, at)
    if min(dims) <= 0:
        raise SourceError(file, f"{at}.3d_dimensions", f"dimensions must be positive, got l w h = {dims}")
    center = _numbers(obj, "3d_location", ("x", "y", "z"), file, at)
    yaw = as_number(obj.get("rotation"), file, f"{at}.rotation")
    check_box(dims, center, yaw, file, at)
    return LabelObject(
        index=i, category=category, center=np.array(center),
        lwh=np.array(dims), yaw=yaw, box2d=box2d,
        occlusion_level=occlusion_level(obj.get("occluded_state")),
        attributes=_attributes(obj, file, at),
    )


MAX_ATTRIBUTE_NESTING = 32
"""Deepest nesting of lists and objects accepted in a label's free-form fields, which are copied
into the record as source_attributes. DAIR-V2X's are flat; orjson parses up to 1024 levels but
writes at most 254, so a deeper value would pass reading and then stop the run at the write."""


def _attributes(obj: dict, file: Path, at: str) -> dict[str, Any]:
    """The label's other fields (source_attributes), refused when nested beyond MAX_ATTRIBUTE_NESTING."""
    attributes = {k: v for k, v in obj.items() if k not in GEOMETRY_KEYS}
    for key, value in attributes.items():
        if isinstance(value, (dict, list)) and _nesting(value) > MAX_ATTRIBUTE_NESTING:
            raise SourceError(file, f"{at}.{key}", f"nested deeper than {MAX_ATTRIBUTE_NESTING} levels "
                              f"(MAX_ATTRIBUTE_NESTING)")
    return attributes


def _nesting(value: Any) -> int:
    """Depth of nested lists and objects (a scalar 0, a flat list 1), without recursion; stops looking past the limit."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            deepest = max(deepest, depth)
            if depth <= MAX_ATTRIBUTE_NESTING:  # deeper than the limit: no need to look further
                stack.extend((v, depth + 1) for v in (item.values() if isinstance(item, dict) else item))
    return deepest


def _numbers(obj: dict, key: str, names: tuple[str, ...], file: Path, at: str) -> list[float]:
    sub = obj.get(key)
    if not isinstance(sub, dict):
        raise SourceError(file, f"{at}.{key}", "missing" if sub is None else f"expected an object with {', '.join(names)}")
    return _read_numbers(sub, names, file, f"{at}.{key}")


def _read_numbers(sub: dict, names: tuple[str, ...], file: Path, where: str) -> list[float]:
    """as_number of each named field; the field's path is spelled out only for an error (hot path)."""
    values = []
    for n in names:
        v = sub.get(n)
        if type(v) is float and math.isfinite(v):
            values.append(v)
        else:
            values.append(as_number(v, file, f"{where}.{n}"))
    return values


def parse_box2d(value: Any, file: Path, where: str) -> np.ndarray:
    """`{xmin, ymin, xmax, ymax}` as [x1, y1, x2, y2]; reversed corners are an error."""
    if not isinstance(value, dict):
        raise SourceError(file, where, "missing" if value is None else "expected an object with xmin, ymin, xmax, ymax")
    box = _read_numbers(value, BOX2D_KEYS, file, where)
    if box[2] < box[0] or box[3] < box[1]:
        raise SourceError(file, where, f"xmax < xmin or ymax < ymin in {box}")
    check_box2d(box, file, where)
    return np.array(box)


BOX2D_KEYS = ("xmin", "ymin", "xmax", "ymax")


def occlusion_level(value: Any) -> int:
    """DAIR-V2X's occluded_state 0/1/2 (number or string) is the contract's level; else 3 (unknown)."""
    try:
        level = int(float(value))
    except (TypeError, ValueError, OverflowError):
        return OCCLUSION_UNKNOWN
    return level if level in (0, 1, 2) and float(value) == level else OCCLUSION_UNKNOWN


# ---------------------------------------------------------------------------------------------
# Ground plane
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GroundEstimate:
    """The ground in the virtual-LiDAR frame and how it was found ("fit" or "level")."""

    plane: Plane
    method: str


def estimate_ground(objects: Sequence[LabelObject]) -> GroundEstimate | None:
    """Ground plane in the virtual-LiDAR frame from the objects' bottoms; None without objects.

    With PLANE_MIN_OBJECTS or more, a plane is fitted (IRLS, so a few boxes on a kerb do not tilt
    it) through all bottom corners; a fit tilted beyond PLANE_MAX_TILT_DEG is discarded. Otherwise
    the plane is level (the virtual LiDAR's z is up) at the median bottom height, which one box
    floating or sunk cannot move much.
    """
    if not objects:
        return None
    if len(objects) >= PLANE_MIN_OBJECTS:
        plane = fit_ground(bottom_corners(objects), LIDAR_UP, PLANE_MIN_OBJECTS, math.radians(PLANE_MAX_TILT_DEG))
        if plane is not None:
            return GroundEstimate(plane, "fit")
    bottom = float(np.median([o.center[2] - o.lwh[2] / 2.0 for o in objects]))
    return GroundEstimate(Plane(LIDAR_UP, -bottom), "level")


def bottom_corners(objects: Sequence[LabelObject]) -> np.ndarray:
    """(N, 4, 3) ground-contact corners (4-7) of every object in the virtual-LiDAR frame."""
    centers = np.array([o.center for o in objects], dtype=np.float64).reshape(-1, 3)
    lwh = np.array([o.lwh for o in objects], dtype=np.float64).reshape(-1, 3)
    return cuboid_corners(centers, lwh, rots_z([o.yaw for o in objects]))[:, list(BOTTOM_CORNERS)]


def plane_to_camera(plane: Plane, ext: Extrinsics) -> Plane:
    """The same plane in the camera frame: n' = R n with R the nearest rotation, through M p + t
    for a point p on it, M the matrix as calibrated (see Extrinsics)."""
    normal = ext.rotation @ plane.normal
    point = ext.calibrated @ (-plane.offset * plane.normal) + ext.translation
    return Plane(normal, -float(normal @ point))


def pitch_from_up(up_in_camera: np.ndarray) -> float:
    """Optical axis below the horizon (radians, positive looking down), as Plane.camera_pitch."""
    return float(math.asin(np.clip(-up_in_camera[2], -1.0, 1.0)))


def camera_pose(estimate: GroundEstimate | None, ext: Extrinsics) -> tuple[Plane | None, float | None, float]:
    """Ground plane in the camera, camera height and pitch read off it.

    Without objects there is no ground height, but the virtual LiDAR's z is up, so the pitch still
    follows from the extrinsics; the plane and the height stay unknown (None).
    """
    if estimate is None:
        return None, None, pitch_from_up(ext.up_in_camera())
    plane = plane_to_camera(estimate.plane, ext)
    return plane, plane.camera_height, plane.camera_pitch


# ---------------------------------------------------------------------------------------------
# Frames, sources and groups
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameInfo:
    """One data_info.json entry with the DAIR frame id taken from its image path."""

    position: int  # index in data_info.json, for messages
    key: str  # DAIR's id, e.g. "001366"
    info: dict[str, Any]


@dataclass(frozen=True)
class SourceTree:
    """Where the infrastructure side lives and what data_info.json says (or the layout implies)."""

    root: Path
    data_info: Path | None  # None: no data_info.json, frames found from the folder layout
    frames: list[FrameInfo]
    errors: dict[str, SourceError]  # entries that cannot become frames, reported as skips


def locate_root(src: Path) -> Path:
    """The infrastructure-side folder: SRC itself, or SRC/infrastructure-side for a DAIR-V2X-C root."""
    src = Path(src)
    if (src / DATA_INFO).is_file() or (src / "image").is_dir():
        return src
    side = src / INFRASTRUCTURE_SIDE
    if (side / DATA_INFO).is_file() or (side / "image").is_dir():
        return side
    if not src.exists():
        raise SourceError(src, "", "does not exist")
    raise SourceError(src, "", f"no {DATA_INFO} or image/ folder here or in {INFRASTRUCTURE_SIDE}/")


def read_tree(src: Path) -> SourceTree:
    """Read data_info.json (or list image/ when it is absent) into frames keyed by DAIR id."""
    root = locate_root(src)
    path = root / DATA_INFO
    if not path.is_file():
        return SourceTree(root, None, *_frames_from_layout(root))
    data = read_json(path, max_bytes=DATA_INFO_MAX_BYTES)
    if not isinstance(data, list):
        raise SourceError(path, "", f"expected a JSON list of frames, got {type(data).__name__}")
    frames: list[FrameInfo] = []
    errors: dict[str, SourceError] = {}
    seen: dict[str, int] = {}
    for i, entry in enumerate(data):
        try:
            frame = _frame_info(entry, i, path)
            if frame.key in seen:
                raise SourceError(path, f"[{i}].image_path", f"frame {frame.key} is listed twice (first at [{seen[frame.key]}])")
        except SourceError as exc:
            errors[f"#{i}"] = exc
            continue
        seen[frame.key] = i
        frames.append(frame)
    return SourceTree(root, path, frames, errors)


def _frame_info(entry: Any, i: int, path: Path) -> FrameInfo:
    if not isinstance(entry, dict):
        raise SourceError(path, f"[{i}]", f"expected a JSON object, got {type(entry).__name__}")
    image = entry.get("image_path")
    if not isinstance(image, str) or not image.strip():
        raise SourceError(path, f"[{i}].image_path", "missing" if image is None else f"expected a path, got {_short(image)}")
    key = Path(image).stem
    if not FRAME_ID_PATTERN.match(key):
        raise SourceError(path, f"[{i}].image_path", f"frame id {key!r} must be letters, digits, '.', '_' or '-'")
    return FrameInfo(i, key, entry)


def _frames_from_layout(root: Path) -> tuple[list[FrameInfo], dict[str, SourceError]]:
    """Without data_info.json, every image/{id}.jpg is a frame and the other files follow the layout.

    An image whose name is no frame id, or a second image of one id (X.jpg and X.png), is returned
    as an error, reported as a skip by name, as data_info.json's entries are.
    """
    images = sorted(p for p in (root / "image").iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    frames: list[FrameInfo] = []
    errors: dict[str, SourceError] = {}
    first: dict[str, Path] = {}
    for p in images:
        if not FRAME_ID_PATTERN.match(p.stem):
            errors[f"image/{p.name}"] = SourceError(p, "", f"frame id {p.stem!r} must be letters, digits, '.', '_' or '-'")
        elif p.stem in first:
            errors[f"image/{p.name}"] = SourceError(p, "", f"frame {p.stem} already has an image, {first[p.stem].name}")
        else:
            first[p.stem] = p
            frames.append(FrameInfo(len(frames), p.stem, {"image_path": f"image/{p.name}"}))
    return frames, errors


def detect_source(tree: SourceTree) -> str:
    """dair-v2x-c when data_info carries batch fields or the tree has DAIR-V2X-C's folders, else dair-v2x-i."""
    if any(k in f.info for f in tree.frames for k in C_MARKERS):
        return SOURCE_C
    if (tree.root / "calib" / "virtuallidar_to_world").is_dir():
        return SOURCE_C
    if tree.root.name == INFRASTRUCTURE_SIDE and (tree.root.parent / "vehicle-side").is_dir():
        return SOURCE_C
    return SOURCE_I


def assign_groups(frames: Sequence[FrameInfo], source: str, prefer: str = "batch",
                  gap_s: float = DEFAULT_GROUP_GAP_S, file: Path | None = None) -> tuple[dict[str, str | None], dict[str, SourceError]]:
    """A group per frame, so that a split keeps neighbouring frames on one side.

    Methods, tried in order starting with `prefer` (then batch, time, intersection): `batch`, the
    DAIR-V2X-C sequence (`batch_id`); `time`, runs of timestamps (image, else point cloud) of one
    intersection with no gap above `gap_s`; `intersection`, the whole `intersection_loc`. A frame
    none of them applies to gets no group (None). Bad timestamps are returned as errors.
    """
    order = [prefer] + [m for m in GROUP_METHODS if m != prefer]
    stamps, errors = _timestamps(frames, file)
    runs = _time_runs(frames, stamps, source, gap_s)
    groups: dict[str, str | None] = {}
    for f in frames:
        groups[f.key] = None
        for method in order:
            group = _group_for(f, method, source, runs)
            if group is not None:
                groups[f.key] = group
                break
    return groups, errors


def _text(info: dict[str, Any], key: str) -> str | None:
    value = info.get(key)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = str(value)
    return value.strip() if isinstance(value, str) and value.strip() else None


def _group_for(f: FrameInfo, method: str, source: str, runs: dict[str, str]) -> str | None:
    if method == "batch":
        batch = _text(f.info, "batch_id")
        return f"{source}-batch-{batch}" if batch else None
    if method == "time":
        return runs.get(f.key)
    loc = _text(f.info, "intersection_loc")
    return f"{source}-{loc}" if loc else None


def _timestamps(frames: Sequence[FrameInfo], file: Path | None) -> tuple[dict[str, int], dict[str, SourceError]]:
    stamps: dict[str, int] = {}
    errors: dict[str, SourceError] = {}
    for f in frames:
        for key in TIMESTAMP_KEYS:
            raw = _text(f.info, key)
            if raw is None:
                continue
            if not re.fullmatch(r"\d+", raw):
                errors[f.key] = SourceError(file or DATA_INFO, f"[{f.position}].{key}",
                                            f"expected microseconds as digits, got {_short(f.info[key])}")
            else:
                stamps[f.key] = int(raw)
            break
    return stamps, errors


def _time_runs(frames: Sequence[FrameInfo], stamps: dict[str, int], source: str, gap_s: float) -> dict[str, str]:
    """Group name per timestamped frame: runs without a gap above gap_s, per intersection."""
    by_place: dict[str, list[tuple[int, str]]] = {}
    for f in frames:
        if f.key in stamps:
            by_place.setdefault(_text(f.info, "intersection_loc") or "", []).append((stamps[f.key], f.key))
    gap_us = gap_s * 1e6
    runs: dict[str, str] = {}
    for items in by_place.values():
        items.sort()
        name, previous = "", None
        for stamp, key in items:
            if previous is None or stamp - previous > gap_us:
                name = f"{source}-run-{key}"
            runs[key] = name
            previous = stamp
    return runs


# ---------------------------------------------------------------------------------------------
# Converting one frame
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DairOptions:
    source: str = "auto"  # auto, dair-v2x-i or dair-v2x-c
    label: str = "camera"  # which label set gives the boxes
    fallback_virtuallidar: bool = False  # use label/virtuallidar where label/camera is missing
    images: Path | None = None  # another folder to look for images in (by file name)
    group_by: str = "batch"
    group_gap_s: float = DEFAULT_GROUP_GAP_S


class DairConverter:
    """Turns DAIR frame ids into ConvertedFrames; the frame loop itself is omnigen.converters.common's."""

    def __init__(self, src: Path, options: DairOptions = DairOptions(), side: DairSide = INFRASTRUCTURE):
        self.options = options
        self.side = side
        self.tree = read_tree(src)
        self.root = self.tree.root
        self.source = detect_source(self.tree) if options.source == "auto" else options.source
        self.frames = {f.key: f for f in self.tree.frames}
        self.groups, group_errors = assign_groups(self.tree.frames, self.source, options.group_by,
                                                  options.group_gap_s, self.tree.data_info)
        self.errors: dict[str, SourceError] = {**self.tree.errors, **group_errors}

    def keys(self) -> list[str]:
        """Frame ids in sorted order, then the data_info entries that could not become frames."""
        return sorted(self.frames) + sorted(k for k in self.errors if k not in self.frames)

    def convert(self, key: str) -> ConvertedFrame:
        """One frame; holds no open files, so it is safe to call in forked workers."""
        return self.convert_posed(key)[0]

    def convert_posed(self, key: str) -> tuple[ConvertedFrame, Extrinsics, Path]:
        """One frame, and the extrinsics its boxes were projected with and their file: read once,
        so that a caller placing the camera in the world from them (dair_cooperative) uses the
        very values the labels were made with."""
        if key in self.errors:
            raise self.errors[key]
        f = self.frames[key]
        image, named = self.image_path(f)
        width, height = source_image_size(image, named)
        K = parse_intrinsics(*self._read(f, INTRINSIC_KEYS, INTRINSIC_DIRS))
        ext_data, ext_path = self._read(f, self.side.extrinsic_keys, self.side.extrinsic_dirs)
        ext = parse_extrinsics(ext_data, ext_path)
        label_file, label_set, named_by = self.label_path(f)
        label = parse_label(read_json(label_file, f"{named_by}, frame {f.key}"), label_file)
        objects = make_objects(label.objects, K, ext, width, height, label_set)
        estimate = estimate_ground(label.objects)
        plane, camera_height, camera_pitch = camera_pose(estimate, ext)
        frame_id = self.frame_id(f.key)
        suffix = named.suffix.lower()
        record = FrameRecord(
            frame_id=frame_id, source=self.source, view=self.side.view, image=image_relpath(frame_id, suffix),
            width=width, height=height, K=K, objects=[o for o in objects if o is not None], ignore_regions=label.ignore_regions,
            ground_plane=plane, camera_height=camera_height, camera_pitch=camera_pitch, group=self.groups.get(f.key),
        )
        return ConvertedFrame(record, ImageSource(suffix, path=image), frame_stats(objects, estimate, label_set)), \
            ext, ext_path

    def frame_id(self, key: str) -> str:
        """The record's frame id for a DAIR id: `<source>-<side tag><id>`."""
        return f"{self.source}-{self.side.tag}{key}"

    # -- paths ------------------------------------------------------------------------------------
    # Every path a frame needs is resolved (links followed) and must stay inside SRC (--images DIR
    # for images found there); the file is then read through omnigen.converters.common's size-capped,
    # regular-file-only reads. docs/untrusted-inputs.md says why.

    def image_path(self, f: FrameInfo) -> tuple[Path, Path]:
        """(the image file, links resolved, to decode and link; the path as named, for its suffix)."""
        value = f.info["image_path"]
        named_by = f"named by {self.data_info_name}[{f.position}].image_path"
        named = self.root / value
        path = source_path(self.root, value, f.key, named_by)
        if self.options.images is not None and not path.exists():
            named = Path(self.options.images) / Path(value).name
            path = source_path(self.options.images, named.name, f.key, f"{named_by}, looked up in --images")
        return path, named

    def label_path(self, f: FrameInfo) -> tuple[Path, str, str]:
        """The label file for the chosen set, or label/virtuallidar where allowed and needed; the
        set it belongs to; who named it."""
        wanted = self.options.label
        labels = self.side.label_keys, self.side.label_dirs
        path, named_by = self.resolve(f, labels[0][wanted], labels[1][wanted])
        if wanted == "camera" and self.options.fallback_virtuallidar and not path.exists():
            other, other_named_by = self.resolve(f, labels[0]["virtuallidar"], labels[1]["virtuallidar"])
            if other.exists():
                return other, "virtuallidar", other_named_by
        if not path.exists():
            hint = "; --fallback-virtuallidar uses label/virtuallidar instead" if wanted == "camera" else ""
            raise SourceError(path, "", f"missing ({named_by}){hint}")
        return path, wanted, named_by

    def resolve(self, f: FrameInfo, keys: tuple[str, ...], dirs: tuple[str, ...]) -> tuple[Path, str]:
        """A file named by data_info (first key present), else by the folder layout; and who named it.

        The path is returned with links resolved, and only when it lies inside SRC.
        """
        for k in keys:
            value = f.info.get(k)
            if isinstance(value, str) and value.strip():
                named_by = f"named by {self.data_info_name}[{f.position}].{k}"
                return source_path(self.root, value, f.key, named_by), named_by
        candidates = [self.root / d / f"{f.key}.json" for d in dirs]
        chosen = next((path for path in candidates if path.exists()), candidates[0])
        named_by = "expected by the folder layout"
        return source_path(self.root, chosen.relative_to(self.root), f.key, named_by), named_by

    def _read(self, f: FrameInfo, keys: tuple[str, ...], dirs: tuple[str, ...]) -> tuple[Any, Path]:
        path, named_by = self.resolve(f, keys, dirs)
        return read_json(path, f"{named_by}, frame {f.key}"), path

    @property
    def data_info_name(self) -> str:
        return str(self.tree.data_info) if self.tree.data_info is not None else DATA_INFO


STAT_KEYS = ("objects_outside_image", "ground_plane_fitted", "ground_plane_level", "ground_plane_none",
             "frames_label_virtuallidar")
"""Counts each frame reports; run_conversion sums them into the report and the manifest."""


def frame_stats(objects: Sequence[ObjectRecord | None], estimate: GroundEstimate | None, label_set: str) -> dict[str, int]:
    method = "none" if estimate is None else {"fit": "fitted", "level": "level"}[estimate.method]
    return {
        "objects_outside_image": sum(o is None for o in objects),
        "ground_plane_fitted": int(method == "fitted"),
        "ground_plane_level": int(method == "level"),
        "ground_plane_none": int(method == "none"),
        "frames_label_virtuallidar": int(label_set == "virtuallidar"),
    }


def make_object(o: LabelObject, K: np.ndarray, ext: Extrinsics, width: int, height: int,
                label_set: str) -> ObjectRecord | None:
    """The record of one labelled object; None when its cuboid misses the image.

    The reference for make_objects, which the converter uses (tests check they agree).
    """
    box = box_from_dair(o.center, o.lwh, o.yaw, ext.rotation, ext.translation, ext.calibrated)
    attributes = dict(o.attributes)
    attributes["label_set"] = label_set
    return ObjectRecord.from_box(o.category, o.index + 1, box, K, width, height,
                                 occlusion_level=o.occlusion_level, bbox_source=o.box2d,
                                 source_attributes=attributes)


def make_objects(objects: Sequence[LabelObject], K: np.ndarray, ext: Extrinsics, width: int, height: int,
                 label_set: str) -> list[ObjectRecord | None]:
    """make_object for every object of a frame at once, with identical records.

    Why: one object at a time, numpy's and shapely's per-call costs were most of a frame's time;
    here boxes, projection and self-occlusion are whole-array operations (omnigen.geometry's
    batch functions, which agree bit for bit with the per-box ones).
    """
    if not objects:
        return []
    lwh = np.array([o.lwh for o in objects])
    centers, rotations = boxes_from_dair(np.array([o.center for o in objects]), np.array([o.yaw for o in objects]),
                                         ext.rotation, ext.translation, ext.calibrated)
    proj = project_boxes(cuboid_corners(centers, lwh, rotations), K, width, height)
    occluded = self_occluded_corners_batch(centers, lwh, rotations)
    has_bbox = proj.has_bbox().tolist()
    truncation = proj.truncation.tolist()
    records: list[ObjectRecord | None] = []
    for i, o in enumerate(objects):
        if not has_bbox[i]:
            records.append(None)
            continue
        attributes = dict(o.attributes)
        attributes["label_set"] = label_set
        records.append(ObjectRecord(
            category=o.category, instance_id=o.index + 1, box=Box3D(centers[i], lwh[i], rotations[i]),
            keypoints=proj.keypoints[i], in_image=proj.in_image[i], behind_camera=proj.behind_camera[i],
            occluded=occluded[i], bbox=proj.bbox[i], truncation=truncation[i], occlusion_level=o.occlusion_level,
            bbox_source=o.box2d, source_attributes=attributes))
    return records


def read_image_size(path: Path) -> tuple[int, int]:
    """(width, height) of a whole image: header within the pixel cap, then decoded (see source_image_size)."""
    return source_image_size(path, path)


# ---------------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------------


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("src", type=Path, help="DAIR-V2X-I folder, DAIR-V2X-C infrastructure-side folder, or the DAIR-V2X-C root")
    add_common_arguments(p)
    p.add_argument("--source", choices=("auto", SOURCE_I, SOURCE_C), default="auto",
                   help="which dataset this is (auto: dair-v2x-c when data_info has batch fields, else dair-v2x-i)")
    p.add_argument("--label", choices=LABEL_SETS, default="camera",
                   help="label set giving the boxes: camera (fitted to the image; default) or virtuallidar")
    p.add_argument("--fallback-virtuallidar", action="store_true",
                   help="where label/camera is missing, use label/virtuallidar (recorded per object as label_set)")
    p.add_argument("--images", type=Path, default=None,
                   help="folder to look for images in by file name when SRC/image_path does not exist")
    p.add_argument("--group-by", choices=GROUP_METHODS, default="batch",
                   help="first grouping to try: batch (DAIR-V2X-C batch_id), time (timestamp runs) or intersection")
    p.add_argument("--side", choices=("both", "infrastructure", "vehicle"), default="both",
                   help="on a DAIR-V2X-C cooperative root: both sides, paired (default), or one; "
                        "infrastructure converts as without cooperative/")
    p.add_argument("--group-gap", type=number(*GROUP_GAP_RANGE_S), default=DEFAULT_GROUP_GAP_S, metavar="SECONDS",
                   help="largest timestamp gap inside one time run (default %(default)g)")


def options_from_args(args: argparse.Namespace) -> DairOptions:
    return DairOptions(source=args.source, label=args.label, fallback_virtuallidar=args.fallback_virtuallidar,
                       images=args.images, group_by=args.group_by, group_gap_s=args.group_gap)


def make_converter(args: argparse.Namespace) -> tuple[Any, dict[str, Any]]:
    """The plain converter, or the cooperative one (omnigen.converters.dair_cooperative) on a
    DAIR-V2X-C cooperative root unless --side infrastructure; and what the manifest adds for it."""
    from omnigen.converters.dair_cooperative import CooperativeConverter, check_side, is_cooperative

    side = getattr(args, "side", "both")
    check_side(args.src, side)
    if is_cooperative(args.src) and side != "infrastructure":
        return CooperativeConverter(args.src, options_from_args(args), side), {"side": side}
    return DairConverter(args.src, options_from_args(args)), {}


def run(args: argparse.Namespace) -> int:
    converter, extra = make_converter(args)
    keys = select_keys(converter.keys(), args.limit, converter.root)
    o = converter.options
    conversion = {"converter": "dair", "source": converter.source, "label": o.label,
                  "fallback_virtuallidar": o.fallback_virtuallidar, "group_by": o.group_by, "group_gap_s": o.group_gap_s,
                  **extra}
    report = run_conversion(keys, converter.convert, args.out, link=args.link, strict=args.strict,
                            inputs=[args.src] + ([args.images] if args.images else []),
                            desc=f"dair {converter.source}", manifest_extra={"conversion": conversion},
                            workers=args.workers, durable=args.durable)
    code = print_report(f"convert dair ({converter.source}) -> {args.out}", report)
    s = report.stats
    print(f"  ground plane: fitted in {s['ground_plane_fitted']} frames, level at the median bottom in "
          f"{s['ground_plane_level']}, none (no objects) in {s['ground_plane_none']}; "
          f"objects with no part in the image (left out): {s['objects_outside_image']}; "
          f"frames labelled from label/virtuallidar: {s['frames_label_virtuallidar']}")
    if extra:
        print(f"  cooperative: frames without camera_to_world (a world calibration absent): "
              f"{s['frames_camera_to_world_null']}; infrastructure frames also in a later pair (kept the first): "
              f"{s['infrastructure_frames_in_a_later_pair']}")
    return code
