"""The UrbanOmniView contract, encoded once.

Every producer (renderer, converters) and consumer (merge, exports, stats, detector, BEV head,
evaluators) imports its constants from here, so that a change to the contract is a change to one
file. The prose version lives in docs/conventions.md.
"""

from __future__ import annotations

import numpy as np

SCHEMA_VERSION = 2
"""Version of the per-frame record layout that omnigen writes; bumped on any incompatible change.
Schema 2 adds the sequence and cooperative fields (SCHEMA2_FRAME_FIELDS, SCHEMA2_OBJECT_FIELDS)."""

READABLE_SCHEMA_VERSIONS: tuple[int, ...] = (1, 2)
"""Versions a record may have and still be read: a schema-1 record reads with the schema-2 fields
null, so datasets written before them stay usable (merged, exported, trained on) as they are."""

SCHEMA2_FRAME_FIELDS: tuple[str, ...] = ("sequence", "timestamp", "pair", "camera_to_world")
SCHEMA2_OBJECT_FIELDS: tuple[str, ...] = ("track_id", "velocity")
"""The keys schema 2 added: required (each may be null) in a schema-2 record, absent from a schema-1 one."""

# ---------------------------------------------------------------------------------------------
# The eight keypoints
# ---------------------------------------------------------------------------------------------
NUM_KEYPOINTS = 8

CORNER_NAMES: tuple[str, ...] = (
    "top_front_left",
    "top_front_right",
    "top_rear_right",
    "top_rear_left",
    "bottom_front_left",
    "bottom_front_right",
    "bottom_rear_right",
    "bottom_rear_left",
)

CORNER_SIGNS = np.array(
    [
        [+1, +1, +1],
        [+1, -1, +1],
        [-1, -1, +1],
        [-1, +1, +1],
        [+1, +1, -1],
        [+1, -1, -1],
        [-1, -1, -1],
        [-1, +1, -1],
    ],
    dtype=np.float64,
)
"""Sign of each corner along the object's (x forward, y left, z up) axes; times dims/2."""

TOP_CORNERS = (0, 1, 2, 3)
BOTTOM_CORNERS = (4, 5, 6, 7)
"""The ground-contact corners, the ones the BEV head rectifies."""
FRONT_CORNERS = (0, 1, 4, 5)
REAR_CORNERS = (2, 3, 6, 7)
"""The front and rear faces' corners; each rear corner is its front corner turned (TURN_IDX), slot
for slot, so sums over the two run in the same order (detector/model/heading.py's exact antisymmetry)."""

FLIP_IDX: tuple[int, ...] = (1, 0, 3, 2, 5, 4, 7, 6)
"""Permutation of the corners under a horizontal image flip (left and right swap)."""

TURN_IDX: tuple[int, ...] = (2, 3, 0, 1, 6, 7, 4, 5)
"""The same cuboid turned 180 degrees about its vertical axis: front and rear swap (and with them
left and right). A detector that cannot tell an object's front from its back predicts this order."""

SKELETON: tuple[tuple[int, int], ...] = (
    (0, 1), (1, 2), (2, 3), (3, 0),  # top face
    (4, 5), (5, 6), (6, 7), (7, 4),  # bottom face
    (0, 4), (1, 5), (2, 6), (3, 7),  # verticals
)
"""The 12 cuboid edges as 0-based corner pairs (COCO's skeleton is 1-based; see formats/coco.py)."""

# COCO visibility written by every exporter.
V_OUTSIDE = 0  # outside the image or behind the camera; written as 0 0 0
V_OCCLUDED = 1  # in the image, hidden
V_VISIBLE = 2  # in the image and visible

NEAR_PLANE = 0.1
"""Metres. A corner closer than this along the optical axis counts as behind the camera; the
cuboid is clipped at this plane before its 2D box and truncation are computed."""

# ---------------------------------------------------------------------------------------------
# Sources, views, classes
# ---------------------------------------------------------------------------------------------
SOURCES: tuple[str, ...] = ("synthetic", "kitti", "dair-v2x-i", "dair-v2x-c")
VIEWS: tuple[str, ...] = ("ego", "infrastructure", "aerial")

FINE_CLASSES: tuple[str, ...] = (
    "car",
    "van",
    "truck",
    "bus",
    "tram",
    "pedestrian",
    "cyclist",
    "motorcyclist",
    "tricyclist",
    "barrow",
    "traffic_cone",
    "misc",
)
CLASS_INDEX = {name: i for i, name in enumerate(FINE_CLASSES)}

COARSE_TAXONOMY: dict[str, str] = {
    "car": "vehicle",
    "van": "vehicle",
    "truck": "vehicle",
    "bus": "vehicle",
    "tram": "vehicle",
    "pedestrian": "person",
    "cyclist": "bike",
    "motorcyclist": "bike",
    "tricyclist": "bike",
}
"""Fine class -> coarse class. Fine classes not listed (barrow, traffic_cone, misc) are dropped."""

KITTI_CLASSES: dict[str, str] = {
    "Car": "car",
    "Van": "van",
    "Truck": "truck",
    "Tram": "tram",
    "Misc": "misc",
    "Pedestrian": "pedestrian",
    "Person_sitting": "pedestrian",
    "Cyclist": "cyclist",
}
KITTI_IGNORE = ("DontCare",)

DAIR_CLASSES: dict[str, str] = {  # keys lower-case: DAIR-V2X names are compared case-insensitively
    "car": "car",
    "van": "van",
    "truck": "truck",
    "bus": "bus",
    "pedestrian": "pedestrian",
    "cyclist": "cyclist",
    "motorcyclist": "motorcyclist",
    "tricyclist": "tricyclist",
    "barrowlist": "barrow",
    "trafficcone": "traffic_cone",
}

# ---------------------------------------------------------------------------------------------
# Occlusion levels
# ---------------------------------------------------------------------------------------------
OCCLUSION_FULLY_VISIBLE = 0
OCCLUSION_PARTLY = 1
OCCLUSION_LARGELY = 2
OCCLUSION_UNKNOWN = 3


def occlusion_level_from_fraction(fraction: float | None) -> int:
    """Synthetic rule of the contract: < 0.1 -> 0, < 0.5 -> 1, else 2; unknown -> 3."""
    if fraction is None or not np.isfinite(fraction):
        return OCCLUSION_UNKNOWN
    if fraction < 0.1:
        return OCCLUSION_FULLY_VISIBLE
    if fraction < 0.5:
        return OCCLUSION_PARTLY
    return OCCLUSION_LARGELY


# KITTI's official difficulty: (name, min 2D-box height px, max occluded level, max truncation).
DIFFICULTIES: tuple[tuple[str, float, int, float], ...] = (
    ("easy", 40.0, 0, 0.15),
    ("moderate", 25.0, 1, 0.30),
    ("hard", 25.0, 2, 0.50),
)


def coco_visibility(in_image: np.ndarray, behind_camera: np.ndarray, occluded: np.ndarray) -> np.ndarray:
    """COCO v per corner: 2 visible, 1 in image but occluded, 0 outside or behind the camera."""
    inside = np.asarray(in_image, bool) & ~np.asarray(behind_camera, bool)
    v = np.where(np.asarray(occluded, bool), V_OCCLUDED, V_VISIBLE)
    return np.where(inside, v, V_OUTSIDE).astype(np.int64)
