"""KITTI's conventions: its boxes, class names, observation angle and the text of its label and
calib files.

KITTI labels a box by dims h w l, the bottom-face centre `location` in the rectified camera-0 frame
and `rotation_y` = ry about the camera's y: forward = (cos ry, 0, -sin ry), left = (sin ry, 0,
cos ry), up = (0, -1, 0). Camera 2's offset from camera 0 is carried by P2's last column. KITTI can
only say upright boxes in a level camera; for pitched cameras the rule is box_to_kitti's:
location = centre + (0, h/2, 0) along the camera's y (so KITTI tools get the true centre back),
rotation_y = the heading of the box's forward axis projected onto the camera's x-z plane; the tilt
is lost. Why one module: the converter (converters/kitti.py) reads KITTI, the exporter
(converters/kitti_export.py) and the detector's metric-3D labels (detector/bev/lift.py,
detector/calib_command.py) write it, and all of them must agree. Every choice:
docs/converters-kitti.md.
"""

from __future__ import annotations

import math
import re

import numpy as np

from omnigen.conventions import KITTI_CLASSES
from omnigen.formats.checks import is_finite, non_finite
from omnigen.geometry import Box3D, wrap_angle
from omnigen.record import FrameRecord, ObjectRecord

# ---------------------------------------------------------------------------------------------
# Boxes
# ---------------------------------------------------------------------------------------------


def kitti_rotation(ry: float) -> np.ndarray:
    """Object-to-camera rotation of a KITTI box with rotation_y = ry (about the camera's y)."""
    c, s = math.cos(ry), math.sin(ry)
    forward = [c, 0.0, -s]
    left = [s, 0.0, c]
    up = [0.0, -1.0, 0.0]
    return np.array([forward, left, up], dtype=np.float64).T


def camera_offset_from_projection(P: np.ndarray) -> np.ndarray:
    """Translation t from the rectified camera-0 frame to the camera of P = K [I | t].

    KITTI's P2 carries camera 2's offset in its last column (K t), about 45.76 px / fx in x.
    """
    P = np.asarray(P, dtype=np.float64).reshape(3, 4)
    return np.linalg.solve(P[:, :3], P[:, 3])


def box_from_kitti(h: float, w: float, l: float, x: float, y: float, z: float, ry: float,
                   camera_offset: np.ndarray | None = None) -> Box3D:
    """A KITTI label (dims h w l, bottom-centre location in camera 0, rotation_y) as a Box3D.

    `camera_offset` moves it into the image's camera (camera_offset_from_projection(P2)).
    """
    center = np.array([x, y - h / 2.0, z], dtype=np.float64)
    if camera_offset is not None:
        center = center + np.asarray(camera_offset, dtype=np.float64)
    return Box3D(center, [l, w, h], kitti_rotation(ry))


def box_to_kitti(box: Box3D, camera_offset: np.ndarray | None = None) -> tuple[float, float, float, float, float, float, float]:
    """A Box3D as KITTI (h, w, l, x, y, z, ry) in camera 0.

    KITTI assumes upright objects in a level camera. For a pitched camera we keep what KITTI
    tools reconstruct exact: location = centre + (0, h/2, 0), so `location - (0, h/2, 0)` gives
    back the true centre, and ry is the heading of the forward axis projected onto the camera's
    x-z plane. The tilt itself is lost, as it must be in KITTI's format.
    """
    l, w, h = (float(v) for v in box.dims)
    center = box.center - (np.asarray(camera_offset, dtype=np.float64) if camera_offset is not None else 0.0)
    f = box.forward
    ry = math.atan2(-f[2], f[0])
    return h, w, l, float(center[0]), float(center[1] + h / 2.0), float(center[2]), ry


def kitti_alpha(ry: float, x: float, z: float) -> float:
    """KITTI's observation angle alpha = ry - atan2(x, z), wrapped to [-pi, pi)."""
    return wrap_angle(ry - math.atan2(x, z))


# ---------------------------------------------------------------------------------------------
# Class names
# ---------------------------------------------------------------------------------------------

KITTI_NAMES: dict[str, str] = {fine: name for name, fine in KITTI_CLASSES.items() if name != "Person_sitting"}
"""Fine class -> KITTI name (car -> Car, ..., pedestrian -> Pedestrian)."""
FALLBACK_NAME = "Misc"
"""For fine classes KITTI has no name for (bus, motorcyclist, tricyclist, barrow, traffic_cone):
KITTI's own catch-all, which its evaluation ignores, rather than a name KITTI tools reject."""


def kitti_type(fine: str) -> str:
    """The KITTI name written for a fine class (FALLBACK_NAME where KITTI has none)."""
    return KITTI_NAMES.get(fine, FALLBACK_NAME)


def kitti_name(obj: ObjectRecord) -> str:
    """The object's KITTI class: its original name where it had one (keeps Person_sitting)."""
    original = obj.source_attributes.get("class")
    if isinstance(original, str) and KITTI_CLASSES.get(original) == obj.category:
        return original
    return kitti_type(obj.category)


# ---------------------------------------------------------------------------------------------
# File names and file text
# ---------------------------------------------------------------------------------------------

TR_VELO_TO_CAM = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
"""There is no LiDAR: a virtual one at the camera centre with KITTI's axes (x forward, y left, z
up), so tools that insist on the matrix get a valid one."""
TR_IMU_TO_VELO = np.hstack([np.eye(3), np.zeros((3, 1))])

_KITTI_FRAME = re.compile(r"^kitti-(?:testing-)?(\d{6})$")
_OWN_KEYS = ("truncated", "occluded", "alpha")


def kitti_number(v: float) -> str:
    """Shortest text that reads back as the same double: written labels round-trip exactly."""
    return repr(float(v))


def kitti_file_names(frame_ids: list[str]) -> dict[str, str]:
    """Frame id -> KITTI file number.

    Converted KITTI frames keep their own number (kitti-000123 -> 000123) when that is unambiguous,
    so an exported KITTI split lines up with the original; any other dataset is numbered
    000000, 000001, ... in frame-id order.
    """
    matches = [_KITTI_FRAME.match(f) for f in frame_ids]
    if all(matches):
        numbers = [m.group(1) for m in matches if m]
        if len(set(numbers)) == len(numbers):
            return dict(zip(frame_ids, numbers))
    return {f: f"{i:06d}" for i, f in enumerate(sorted(frame_ids))}


def _own_values(record: FrameRecord, obj: ObjectRecord) -> dict | None:
    """KITTI's own truncated / occluded / alpha where the record kept them (converted KITTI)."""
    attrs = obj.source_attributes
    if record.source == "kitti" and all(k in attrs for k in _OWN_KEYS):
        return attrs
    return None


LABEL_FIELDS = ("alpha", "bbox left", "bbox top", "bbox right", "bbox bottom", "height", "width", "length",
                "location x", "location y", "location z", "rotation_y")
"""The names of a label line's numbers after its `truncated` and `occluded`, in KITTI's order."""


def _check_finite(truncated: float, numbers: list[float], where: str) -> None:
    """Refuse a label line with a value that is not finite (Python would write `inf` or `nan`)."""
    for name, value in zip(("truncated", *LABEL_FIELDS), (truncated, *numbers)):
        if not math.isfinite(value):
            raise non_finite(where, f"KITTI {name}", value)


def label_line(record: FrameRecord, obj: ObjectRecord, derived: bool = False, where: str = "object") -> str:
    """One label_2 line. Values KITTI wrote itself are written back unless `derived`; else
    truncated = truncation, occluded = occlusion_level (3 = unknown), alpha from the location and
    rotation_y, 2D box = bbox. A value that is not finite is refused (NonFiniteError, naming `where`)."""
    with np.errstate(over="ignore", invalid="ignore"):  # overflow is what _check_finite reports
        h, w, l, x, y, z, ry = box_to_kitti(obj.box)
    own = None if derived else _own_values(record, obj)
    if own is not None:
        truncated, occluded, alpha = float(own["truncated"]), int(own["occluded"]), float(own["alpha"])
        box2d = obj.bbox_source if obj.bbox_source is not None else obj.bbox
    else:
        truncated, occluded, alpha = obj.truncation, int(obj.occlusion_level), kitti_alpha(ry, x, z)
        box2d = obj.bbox
    numbers = [alpha, *box2d, h, w, l, x, y, z, ry]
    _check_finite(truncated, numbers, where)
    return f"{kitti_name(obj)} {kitti_number(truncated)} {occluded} " + " ".join(kitti_number(v) for v in numbers)


def dont_care_line(bbox: np.ndarray, where: str = "ignore region") -> str:
    if not is_finite(bbox):
        raise non_finite(where, "KITTI DontCare box", bbox)
    return "DontCare -1 -1 -10 " + " ".join(kitti_number(v) for v in bbox) + " -1 -1 -1 -1000 -1000 -1000 -10"


def label_text(record: FrameRecord, derived: bool = False) -> str:
    """Objects in record order (instance ids ascending for converted KITTI), then ignore regions.
    A value that is not finite is refused (NonFiniteError naming the object or region)."""
    lines = [label_line(record, o, derived, f"objects[{k}]") for k, o in enumerate(record.objects)]
    lines += [dont_care_line(r.bbox, f"ignore_regions[{k}].bbox") for k, r in enumerate(record.ignore_regions)]
    return "".join(f"{line}\n" for line in lines)


def calib_text(K: np.ndarray) -> str:
    """KITTI's seven calib lines. Every P is [K | 0]: the record's camera is the only camera."""
    if not is_finite(K):
        raise non_finite("K", "KITTI calib's P2", K)
    P = np.hstack([np.asarray(K, dtype=np.float64), np.zeros((3, 1))])
    rows = [(f"P{i}", P) for i in range(4)]
    rows += [("R0_rect", np.eye(3)), ("Tr_velo_to_cam", TR_VELO_TO_CAM), ("Tr_imu_to_velo", TR_IMU_TO_VELO)]
    return "".join(f"{name}: " + " ".join(kitti_number(v) for v in m.ravel()) + "\n" for name, m in rows)
