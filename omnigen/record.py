"""The UrbanOmniView record: one frame, its objects and its ignore regions.

A record is plain data (dataclasses holding numpy arrays). On disk it is one JSON document per
frame; `FrameRecord.from_dict` is the only way in and validates every field, so a bad file is
rejected with the frame and the field named instead of failing somewhere downstream.

Keypoints behind the camera are NaN in memory and null in JSON; a NaN anywhere in a JSON
record is an error.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from omnigen.conventions import (
    CLASS_INDEX,
    DIFFICULTIES,
    NUM_KEYPOINTS,
    OCCLUSION_UNKNOWN,
    READABLE_SCHEMA_VERSIONS,
    SCHEMA2_FRAME_FIELDS,
    SCHEMA2_OBJECT_FIELDS,
    SCHEMA_VERSION,
    SOURCES,
    VIEWS,
    coco_visibility,
)
from omnigen.geometry import Box3D, Plane, is_rotation, project_box, self_occluded_corners

DIFFICULTY_NAMES = tuple(d[0] for d in DIFFICULTIES)
FRAME_ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


class RecordError(ValueError):
    """A record that breaks the contract; names the frame, the field and, when known, the file."""

    def __init__(self, frame_id: str | None, field_path: str, message: str, file: str | None = None):
        self.frame_id = frame_id
        self.field = field_path
        self.message = message
        self.file = file
        where = f"{file}: " if file else ""
        super().__init__(f"{where}frame {frame_id or '?'}: field '{field_path}': {message}")


@dataclass
class ObjectRecord:
    """One annotated object. See docs/conventions.md for every field's meaning."""

    category: str
    instance_id: int
    box: Box3D
    keypoints: np.ndarray  # (8, 2) float64, NaN where behind_camera
    in_image: np.ndarray  # (8,) bool
    behind_camera: np.ndarray  # (8,) bool
    occluded: np.ndarray  # (8,) bool
    bbox: np.ndarray  # (4,) x1 y1 x2 y2
    truncation: float
    occlusion: float | None = None  # fraction of the in-image silhouette hidden by others
    occlusion_level: int = OCCLUSION_UNKNOWN
    bbox_source: np.ndarray | None = None
    bbox_visible: np.ndarray | None = None
    difficulty: str | None = None  # KITTI's easy / moderate / hard, where the source defines it
    source_attributes: dict[str, Any] = field(default_factory=dict)
    track_id: int | None = None  # the same physical object across views and instants of a sequence
    velocity: np.ndarray | None = None  # (3,) m/s in the frame of the record's camera_to_world

    @classmethod
    def from_box(cls, category: str, instance_id: int, box: Box3D, K: np.ndarray, width: int, height: int,
                 occluded: np.ndarray | None = None, **fields: Any) -> "ObjectRecord | None":
        """Derive keypoints, flags, bbox and truncation from a cuboid; None if none of it is in the image.

        `occluded` defaults to the cuboid's self-occlusion, which every source can tell.
        """
        proj = project_box(box, K, width, height)
        if proj.bbox is None:
            return None
        if occluded is None:
            occluded = self_occluded_corners(box)
        return cls(category=category, instance_id=instance_id, box=box, keypoints=proj.keypoints,
                   in_image=proj.in_image, behind_camera=proj.behind_camera,
                   occluded=np.asarray(occluded, bool), bbox=proj.bbox, truncation=proj.truncation, **fields)

    @property
    def visibility(self) -> np.ndarray:
        """COCO v per corner (2 visible, 1 occluded, 0 outside the image or behind the camera)."""
        return coco_visibility(self.in_image, self.behind_camera, self.occluded)

    def to_dict(self) -> dict[str, Any]:
        # numpy's tolist gives the same Python floats and bools as per-element conversion, in one call
        behind = np.asarray(self.behind_camera, bool).tolist()
        kp = [None if b else xy for xy, b in zip(np.asarray(self.keypoints, np.float64).tolist(), behind)]
        return {
            "category": self.category,
            "instance_id": int(self.instance_id),
            "track_id": None if self.track_id is None else int(self.track_id),
            "box3d": {
                "center": self.box.center.tolist(),
                "dims": self.box.dims.tolist(),
                "rotation": self.box.rotation.tolist(),
            },
            "velocity": _opt_list(self.velocity),
            "keypoints": kp,
            "in_image": np.asarray(self.in_image, bool).tolist(),
            "behind_camera": behind,
            "occluded": np.asarray(self.occluded, bool).tolist(),
            "bbox": np.asarray(self.bbox, np.float64).tolist(),
            "truncation": float(self.truncation),
            "occlusion": None if self.occlusion is None else float(self.occlusion),
            "occlusion_level": int(self.occlusion_level),
            "bbox_source": None if self.bbox_source is None else np.asarray(self.bbox_source, np.float64).tolist(),
            "bbox_visible": None if self.bbox_visible is None else np.asarray(self.bbox_visible, np.float64).tolist(),
            "difficulty": self.difficulty,
            "source_attributes": self.source_attributes,
        }


@dataclass
class IgnoreRegion:
    """A 2D box the detector must neither be rewarded nor punished for (KITTI DontCare, ...)."""

    bbox: np.ndarray  # (4,) x1 y1 x2 y2
    label: str  # the source's own class name

    def to_dict(self) -> dict[str, Any]:
        return {"bbox": [float(v) for v in self.bbox], "label": self.label}


@dataclass
class SyntheticInfo:
    """What produced a rendered frame; enough to render it again."""

    seed: int
    scene: str
    rig: str
    weather: dict[str, Any]
    lighting: dict[str, Any]
    depth: str  # path of the depth EXR, relative to the dataset root
    instance: str  # path of the 16-bit instance PNG, relative to the dataset root

    def to_dict(self) -> dict[str, Any]:
        return {"seed": int(self.seed), "scene": self.scene, "rig": self.rig, "weather": self.weather,
                "lighting": self.lighting, "depth": self.depth, "instance": self.instance}


@dataclass
class FrameRecord:
    """One image and everything annotated in it, in that image's camera frame."""

    frame_id: str
    source: str
    view: str
    image: str  # relative to the dataset root
    width: int
    height: int
    K: np.ndarray  # (3, 3)
    objects: list[ObjectRecord] = field(default_factory=list)
    ignore_regions: list[IgnoreRegion] = field(default_factory=list)
    ground_plane: Plane | None = None
    camera_height: float | None = None
    camera_pitch: float | None = None
    group: str | None = None  # frames that must stay on one side of a split
    synthetic: SyntheticInfo | None = None
    schema_version: int = SCHEMA_VERSION  # as read; to_dict always writes SCHEMA_VERSION
    sequence: str | None = None  # frames of one world run: one world frame and one clock
    timestamp: float | None = None  # seconds from the sequence's first instant (needs `sequence`)
    pair: str | None = None  # the two frames of a cooperative pair (DAIR-V2X-C vehicle + infrastructure)
    camera_to_world: np.ndarray | None = None  # (4, 4): X_world = M [X_cam; 1], metres

    def to_dict(self) -> dict[str, Any]:
        """The record in the layout of SCHEMA_VERSION: a schema-1 record read and written again
        is upgraded, its schema-2 fields null."""
        return {
            "schema_version": SCHEMA_VERSION,
            "frame_id": self.frame_id,
            "source": self.source,
            "view": self.view,
            "image": self.image,
            "width": int(self.width),
            "height": int(self.height),
            "K": np.asarray(self.K, dtype=np.float64).tolist(),
            "ground_plane": None if self.ground_plane is None else {
                "normal": self.ground_plane.normal.tolist(), "offset": float(self.ground_plane.offset)},
            "camera_height": _opt_float(self.camera_height),
            "camera_pitch": _opt_float(self.camera_pitch),
            "group": self.group,
            "sequence": self.sequence,
            "timestamp": _opt_float(self.timestamp),
            "pair": self.pair,
            "camera_to_world": _opt_list(self.camera_to_world),
            "synthetic": None if self.synthetic is None else self.synthetic.to_dict(),
            "objects": [o.to_dict() for o in self.objects],
            "ignore_regions": [r.to_dict() for r in self.ignore_regions],
        }

    @classmethod
    def from_dict(cls, d: Any, file: str | None = None) -> "FrameRecord":
        """Parse and validate; raises RecordError naming the frame and the field."""
        return _FrameParser(d, file).parse()


def _opt_float(v: float | None) -> float | None:
    return None if v is None else float(v)


def _opt_list(a: np.ndarray | None) -> list | None:
    return None if a is None else np.asarray(a, dtype=np.float64).tolist()


# ---------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------

_MISSING = object()
_NAN_PAIR = (float("nan"), float("nan"))
_CLASS_NAMES = tuple(CLASS_INDEX)
_CLASS_SET = frozenset(CLASS_INDEX)
_PLAIN_NUMBERS = (int, float)  # exact types: bool, a subclass of int, is not a number here
_ROTATION_TOL_AT_ONCE = 0.99e-4
"""The stacked check's rotation tolerance, a hair under the 1e-4 `object` uses, so that a
rounding difference between the two ways of computing R^T R can never let through what
`object` would refuse."""
_TRACK_ID_MAX = 2**31 - 1
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_LAST_ROW_TOL = 1e-9
"""camera_to_world's last row is 0 0 0 1 up to float noise (a pose composed or inverted in float64)."""


class _FrameParser:
    """Reads a frame dict field by field, so every error carries its path."""

    def __init__(self, d: Any, file: str | None):
        self.d = d
        self.file = file
        self.frame_id: str | None = d.get("frame_id") if isinstance(d, dict) and isinstance(d.get("frame_id"), str) else None
        self.version = SCHEMA_VERSION  # the record's, once parse has read it

    def fail(self, path: str, message: str) -> RecordError:
        return RecordError(self.frame_id, path, message, self.file)

    def get(self, d: dict, key: str, path: str) -> Any:
        value = d.get(key, _MISSING)
        if value is _MISSING:
            raise self.fail(path, "missing")
        return value

    def number(self, value: Any, path: str, lo: float = -math.inf, hi: float = math.inf) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(path, f"expected a number, got {type(value).__name__} {value!r}")
        if not math.isfinite(value):
            raise self.fail(path, f"not finite: {value!r}")
        if not lo <= value <= hi:
            raise self.fail(path, f"{value!r} outside [{lo}, {hi}]")
        return float(value)

    def opt_number(self, value: Any, path: str, lo: float = -math.inf, hi: float = math.inf) -> float | None:
        return None if value is None else self.number(value, path, lo, hi)

    def integer(self, value: Any, path: str, lo: int = -(2**31), hi: int = 2**31 - 1) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(path, f"expected an integer, got {value!r}")
        if not lo <= value <= hi:
            raise self.fail(path, f"{value!r} outside [{lo}, {hi}]")
        return value

    def string(self, value: Any, path: str, choices: tuple[str, ...] | None = None) -> str:
        if not isinstance(value, str) or not value:
            raise self.fail(path, f"expected a non-empty string, got {value!r}")
        if choices is not None and value not in choices:
            raise self.fail(path, f"{value!r} is not one of {', '.join(choices)}")
        return value

    def identifier(self, value: Any, path: str) -> str:
        """An id that may name a file or a line of a listing (frame, sequence, pair): a safe name."""
        name = self.string(value, path)
        if not FRAME_ID_PATTERN.match(name):
            raise self.fail(path, f"{name!r} must be letters, digits, '.', '_' or '-'")
        return name

    def opt_identifier(self, value: Any, path: str) -> str | None:
        return None if value is None else self.identifier(value, path)

    def relpath(self, value: Any, path: str) -> str:
        """A file path inside the dataset root: relative, '/'-separated, no '..'."""
        rel = self.string(value, path)
        parts = rel.split("/")
        if rel.startswith(("/", "\\")) or "\\" in rel or (len(rel) > 1 and rel[1] == ":") or ".." in parts or "" in parts:
            raise self.fail(path, f"{rel!r} must be a relative path inside the dataset (no '..', no absolute path)")
        return rel

    def array(self, value: Any, path: str, shape: tuple[int, ...]) -> np.ndarray:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(path, f"expected numbers of shape {shape}") from None
        if arr.shape != shape:
            raise self.fail(path, f"expected shape {shape}, got {arr.shape}")
        if not np.isfinite(arr).all():
            raise self.fail(path, "contains NaN or infinity")
        return arr

    def box3d(self, b: dict, path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """center (3), dims (3), rotation (3, 3): checked as one array in the common case (this
        runs for every object written or read), field by field only to name a culprit."""
        c, d, r = b.get("center"), b.get("dims"), b.get("rotation")
        if (type(c) is list and len(c) == 3 and type(d) is list and len(d) == 3 and type(r) is list
                and len(r) == 3 and all(type(row) is list and len(row) == 3 for row in r)):
            try:
                flat = np.array([*c, *d, *r[0], *r[1], *r[2]], dtype=np.float64)
            except (TypeError, ValueError):
                flat = None
            if flat is not None and np.isfinite(flat).all():
                return flat[:3], flat[3:6], flat[6:].reshape(3, 3)
        return (self.array(self.get(b, "center", path + "center"), path + "center", (3,)),
                self.array(self.get(b, "dims", path + "dims"), path + "dims", (3,)),
                self.array(self.get(b, "rotation", path + "rotation"), path + "rotation", (3, 3)))

    def keypoints(self, raw: list, behind: np.ndarray, path: str) -> np.ndarray:
        """(8, 2) with NaN for null corners; null exactly where behind the camera, finite elsewhere.

        Checked as one array (the common case), then corner by corner only to name a culprit.
        """
        nulls = [k is None for k in raw]
        try:
            arr = np.array([_NAN_PAIR if k is None else k for k in raw], dtype=np.float64)
            ok = arr.shape == (NUM_KEYPOINTS, 2) and bool(np.isfinite(arr[~np.asarray(nulls)]).all())
        except (TypeError, ValueError):
            ok = False
        if ok and nulls == behind.tolist():
            return arr
        for j, k in enumerate(raw):
            kp_path = f"{path}[{j}]"
            if k is None and not behind[j]:
                raise self.fail(kp_path, "null, but the corner is not behind the camera")
            if k is not None and behind[j]:
                raise self.fail(kp_path, "behind the camera, so it must be null")
            if k is not None:
                self.array(k, kp_path, (2,))
        raise self.fail(path, "malformed keypoints")  # unreachable unless the checks above disagree

    def flags(self, value: Any, path: str) -> np.ndarray:
        if not isinstance(value, list) or len(value) != NUM_KEYPOINTS or not all(isinstance(v, bool) for v in value):
            raise self.fail(path, f"expected {NUM_KEYPOINTS} booleans, got {value!r}")
        return np.array(value, dtype=bool)

    def box2d(self, value: Any, path: str) -> np.ndarray:
        arr = self.array(value, path, (4,))
        if arr[2] < arr[0] or arr[3] < arr[1]:
            raise self.fail(path, f"x2 < x1 or y2 < y1 in {arr.tolist()}")
        return arr

    def parse(self) -> FrameRecord:
        d = self.d
        if not isinstance(d, dict):
            raise self.fail("<record>", f"expected a JSON object, got {type(d).__name__}")
        version = self.integer(self.get(d, "schema_version", "schema_version"), "schema_version")
        if version not in READABLE_SCHEMA_VERSIONS:
            readable = ", ".join(map(str, READABLE_SCHEMA_VERSIONS))
            raise self.fail("schema_version", f"this omnigen reads schema {readable}, file has {version}")
        self.version = version
        frame_id = self.identifier(self.get(d, "frame_id", "frame_id"), "frame_id")
        source = self.string(self.get(d, "source", "source"), "source", SOURCES)
        view = self.string(self.get(d, "view", "view"), "view", VIEWS)
        image = self.relpath(self.get(d, "image", "image"), "image")
        width = self.integer(self.get(d, "width", "width"), "width", 1, 65535)
        height = self.integer(self.get(d, "height", "height"), "height", 1, 65535)
        K = self.array(self.get(d, "K", "K"), "K", (3, 3))
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
            raise self.fail("K", f"not a pinhole intrinsic matrix: {K.tolist()}")
        plane = None
        gp = self.get(d, "ground_plane", "ground_plane")
        if gp is not None:
            if not isinstance(gp, dict):
                raise self.fail("ground_plane", "expected an object with normal and offset")
            normal = self.array(self.get(gp, "normal", "ground_plane.normal"), "ground_plane.normal", (3,))
            if abs(np.linalg.norm(normal) - 1) > 1e-3:
                raise self.fail("ground_plane.normal", "not a unit vector")
            plane = Plane(normal, self.number(self.get(gp, "offset", "ground_plane.offset"), "ground_plane.offset"))
        camera_height = self.opt_number(self.get(d, "camera_height", "camera_height"), "camera_height")
        camera_pitch = self.opt_number(self.get(d, "camera_pitch", "camera_pitch"), "camera_pitch", -math.pi, math.pi)
        group = d.get("group")
        if group is not None:
            group = self.string(group, "group")
        world = self.world_fields(d)
        synthetic = self.synthetic(self.get(d, "synthetic", "synthetic"), source)
        objects_raw = self.get(d, "objects", "objects")
        if not isinstance(objects_raw, list):
            raise self.fail("objects", "expected a list")
        objects = self.objects_at_once(objects_raw)
        if objects is None:  # something is off: go object by object to name the field
            objects = [self.object(o, f"objects[{i}]") for i, o in enumerate(objects_raw)]
        self.unique(objects, "instance_id")
        self.unique(objects, "track_id")
        ignore_raw = self.get(d, "ignore_regions", "ignore_regions")
        if not isinstance(ignore_raw, list):
            raise self.fail("ignore_regions", "expected a list")
        ignore = []
        for i, r in enumerate(ignore_raw):
            path = f"ignore_regions[{i}]"
            if not isinstance(r, dict):
                raise self.fail(path, "expected an object")
            ignore.append(IgnoreRegion(self.box2d(self.get(r, "bbox", path + ".bbox"), path + ".bbox"),
                                       self.string(self.get(r, "label", path + ".label"), path + ".label")))
        return FrameRecord(frame_id, source, view, image, width, height, K, objects, ignore, plane,
                           camera_height, camera_pitch, group, synthetic, version, **world)

    def unique(self, objects: list[ObjectRecord], key: str) -> None:
        """Each object's `key` (instance_id, track_id) differs from every other's in the frame; None is no value."""
        seen: set[int] = set()
        for i, o in enumerate(objects):
            value = getattr(o, key)
            if value in seen:
                raise self.fail(f"objects[{i}].{key}", f"duplicate {key} {value}")
            if value is not None:
                seen.add(value)

    def schema2_keys(self, d: dict, keys: tuple[str, ...], path: str) -> dict[str, Any]:
        """The schema-2 keys of a frame or an object: each required (it may be null) in schema 2,
        so that a writer cannot forget one silently; absent in schema 1, read as null."""
        if self.version == 1:
            for key in keys:
                if key in d:
                    raise self.fail(path + key, "not in schema 1 (a record with it has schema_version 2)")
            return dict.fromkeys(keys)
        return {key: self.get(d, key, path + key) for key in keys}

    def world_fields(self, d: dict) -> dict[str, Any]:
        """sequence, timestamp, pair and camera_to_world, checked (null where not known)."""
        raw = self.schema2_keys(d, SCHEMA2_FRAME_FIELDS, "")
        sequence = self.opt_identifier(raw["sequence"], "sequence")
        timestamp = self.opt_number(raw["timestamp"], "timestamp", 0.0)
        if timestamp is not None and sequence is None:
            raise self.fail("timestamp", "a timestamp counts from its sequence's start, and 'sequence' is null")
        pose = raw["camera_to_world"]
        return {"sequence": sequence, "timestamp": timestamp, "pair": self.opt_identifier(raw["pair"], "pair"),
                "camera_to_world": None if pose is None else self.pose(pose, "camera_to_world")}

    def pose(self, value: Any, path: str) -> np.ndarray:
        """A rigid 4x4 transform: a proper rotation (within 1e-4) and a translation, last row 0 0 0 1."""
        m = self.array(value, path, (4, 4))
        if np.abs(m[3] - _LAST_ROW).max() > _LAST_ROW_TOL:
            raise self.fail(path, f"last row must be 0 0 0 1, got {m[3].tolist()}")
        if not is_rotation(m[:3, :3], 1e-4):
            raise self.fail(path, "rotation part not orthonormal with determinant +1 (within 1e-4)")
        return m

    def synthetic(self, s: Any, source: str) -> SyntheticInfo | None:
        if s is None:
            if source == "synthetic":
                raise self.fail("synthetic", "rendered frames must record seed, scene, rig, weather and lighting")
            return None
        if not isinstance(s, dict):
            raise self.fail("synthetic", "expected an object")
        p = "synthetic."
        weather, lighting = self.get(s, "weather", p + "weather"), self.get(s, "lighting", p + "lighting")
        if not isinstance(weather, dict) or not isinstance(lighting, dict):
            raise self.fail(p + "weather", "weather and lighting must be objects")
        return SyntheticInfo(
            seed=self.integer(self.get(s, "seed", p + "seed"), p + "seed", 0, 2**63 - 1),
            scene=self.string(self.get(s, "scene", p + "scene"), p + "scene"),
            rig=self.string(self.get(s, "rig", p + "rig"), p + "rig"),
            weather=weather, lighting=lighting,
            depth=self.relpath(self.get(s, "depth", p + "depth"), p + "depth"),
            instance=self.relpath(self.get(s, "instance", p + "instance"), p + "instance"),
        )

    def objects_at_once(self, raw: list) -> list[ObjectRecord] | None:
        """Every object of a frame checked as a few stacked arrays; None on anything unusual.

        Why: this runs for every record written or read, and one numpy call per field of the
        whole frame costs a fraction of one per field of each object (a converter writes
        12,000 frames in seconds). It accepts only what `object` accepts (exact Python types,
        a slightly tighter rotation tolerance) and returns None for anything else, so that
        `object` finds and names the culprit: it decides, this only saves time.
        """
        if not raw:
            return []
        numbers, kps, nulls, flags, boxes, velocities = [], [], [], [], [], []
        schema1 = self.version == 1
        for o in raw:
            if type(o) is not dict:
                return None
            g = o.get
            c = g("category")
            iid = g("instance_id")
            b = g("box3d")
            bbox = g("bbox")
            t = g("truncation")
            occ = g("occlusion")
            lvl = g("occlusion_level")
            kp = g("keypoints")
            behind, in_image, occluded = g("behind_camera"), g("in_image"), g("occluded")
            diff = g("difficulty")
            tid, vel = g("track_id", _MISSING), g("velocity", _MISSING)
            if (tid is _MISSING) != schema1 or (vel is _MISSING) != schema1:  # required in 2, absent in 1
                return None
            if not schema1 and ((tid is not None and (type(tid) is not int or not 1 <= tid <= _TRACK_ID_MAX))
                                or (vel is not None and (type(vel) is not list or len(vel) != 3))):
                return None
            if vel is not None and vel is not _MISSING:
                velocities.append(vel)
            if (type(c) is not str or c not in _CLASS_SET or type(iid) is not int or not 1 <= iid <= 65535
                    or type(b) is not dict or type(bbox) is not list or len(bbox) != 4
                    or type(t) not in _PLAIN_NUMBERS or type(lvl) is not int or not 0 <= lvl <= 3
                    or (occ is not None and type(occ) not in _PLAIN_NUMBERS)
                    or (diff is not None and (type(diff) is not str or diff not in DIFFICULTY_NAMES))
                    or type(g("source_attributes", {})) is not dict
                    or type(kp) is not list or len(kp) != NUM_KEYPOINTS):
                return None
            ctr, dims, rot = b.get("center"), b.get("dims"), b.get("rotation")
            if not (type(ctr) is list and len(ctr) == 3 and type(dims) is list and len(dims) == 3
                    and type(rot) is list and len(rot) == 3
                    and all(type(row) is list and len(row) == 3 for row in rot)):
                return None
            for f in (behind, in_image, occluded):
                if type(f) is not list or len(f) != NUM_KEYPOINTS:
                    return None
                flags.extend(f)
            for box in (g("bbox_source"), g("bbox_visible")):
                if box is not None:
                    if type(box) is not list or len(box) != 4:
                        return None
                    boxes.append(box)
            numbers.append([*ctr, *dims, *rot[0], *rot[1], *rot[2], *bbox, t, 0.0 if occ is None else occ])
            null = [k is None for k in kp]
            nulls.append(null)
            kps.append([_NAN_PAIR if k is None else k for k in kp])
        if not all(type(v) is bool for v in flags):
            return None
        try:
            num = np.array(numbers, dtype=np.float64)
            kp_all = np.array(kps, dtype=np.float64)
            box_all = np.array(boxes, dtype=np.float64).reshape(-1, 4)
            vel_all = np.array(velocities, dtype=np.float64).reshape(-1, 3)
        except (TypeError, ValueError):
            return None
        n = len(raw)
        null_all = np.array(nulls, dtype=bool)
        flag_all = np.array(flags, dtype=bool).reshape(n, 3, NUM_KEYPOINTS)
        behind_all, in_all, occl_all = flag_all[:, 0], flag_all[:, 1], flag_all[:, 2]
        if (kp_all.shape != (n, NUM_KEYPOINTS, 2) or not np.isfinite(num).all() or not np.isfinite(box_all).all()
                or not np.isfinite(vel_all).all()
                or not np.isfinite(kp_all[~null_all]).all() or not np.array_equal(null_all, behind_all)
                or (in_all & behind_all).any()):
            return None
        rot_all = num[:, 6:15].reshape(n, 3, 3)
        gram = np.einsum("nji,njk->nik", rot_all, rot_all) - np.eye(3)
        bb, tr, oc = num[:, 15:19], num[:, 19], num[:, 20]
        if ((num[:, 3:6] <= 0).any() or np.abs(gram).max() > _ROTATION_TOL_AT_ONCE or (np.linalg.det(rot_all) <= 0).any()
                or (bb[:, 2] < bb[:, 0]).any() or (bb[:, 3] < bb[:, 1]).any() or (box_all[:, 2] < box_all[:, 0]).any()
                or (box_all[:, 3] < box_all[:, 1]).any() or ((tr < 0) | (tr > 1) | (oc < 0) | (oc > 1)).any()):
            return None
        objects = []
        k = v = 0
        for i, o in enumerate(raw):
            src, vis, vel = o.get("bbox_source"), o.get("bbox_visible"), o.get("velocity")
            if src is not None:
                src, k = box_all[k], k + 1
            if vis is not None:
                vis, k = box_all[k], k + 1
            if vel is not None:
                vel, v = vel_all[v], v + 1
            occ = o.get("occlusion")
            objects.append(ObjectRecord(
                category=o["category"], instance_id=o["instance_id"],
                box=Box3D(num[i, 0:3], num[i, 3:6], rot_all[i]), keypoints=kp_all[i],
                in_image=in_all[i], behind_camera=behind_all[i], occluded=occl_all[i], bbox=bb[i],
                truncation=float(tr[i]), occlusion=None if occ is None else float(oc[i]),
                occlusion_level=o["occlusion_level"], bbox_source=src, bbox_visible=vis,
                difficulty=o.get("difficulty"), source_attributes=o.get("source_attributes", {}),
                track_id=o.get("track_id"), velocity=vel,
            ))
        return objects

    def object(self, o: Any, path: str) -> ObjectRecord:
        if not isinstance(o, dict):
            raise self.fail(path, "expected an object")
        p = path + "."
        category = self.string(self.get(o, "category", p + "category"), p + "category", _CLASS_NAMES)
        instance_id = self.integer(self.get(o, "instance_id", p + "instance_id"), p + "instance_id", 1, 65535)
        b = self.get(o, "box3d", p + "box3d")
        if not isinstance(b, dict):
            raise self.fail(p + "box3d", "expected an object with center, dims, rotation")
        center, dims, rotation = self.box3d(b, p + "box3d.")
        if (dims <= 0).any():
            raise self.fail(p + "box3d.dims", f"dimensions must be positive, got {dims.tolist()}")
        if not is_rotation(rotation, 1e-4):
            raise self.fail(p + "box3d.rotation", "not a proper rotation matrix")
        behind = self.flags(self.get(o, "behind_camera", p + "behind_camera"), p + "behind_camera")
        kp_raw = self.get(o, "keypoints", p + "keypoints")
        if not isinstance(kp_raw, list) or len(kp_raw) != NUM_KEYPOINTS:
            n = len(kp_raw) if isinstance(kp_raw, list) else type(kp_raw).__name__
            raise self.fail(p + "keypoints", f"expected {NUM_KEYPOINTS} keypoints, got {n}")
        keypoints = self.keypoints(kp_raw, behind, p + "keypoints")
        in_image = self.flags(self.get(o, "in_image", p + "in_image"), p + "in_image")
        if (in_image & behind).any():
            raise self.fail(p + "in_image", "a corner behind the camera cannot be in the image")
        occluded = self.flags(self.get(o, "occluded", p + "occluded"), p + "occluded")
        bbox = self.box2d(self.get(o, "bbox", p + "bbox"), p + "bbox")
        truncation = self.number(self.get(o, "truncation", p + "truncation"), p + "truncation", 0.0, 1.0)
        occlusion = self.opt_number(o.get("occlusion"), p + "occlusion", 0.0, 1.0)
        level = self.integer(self.get(o, "occlusion_level", p + "occlusion_level"), p + "occlusion_level", 0, 3)
        bbox_source = o.get("bbox_source")
        bbox_visible = o.get("bbox_visible")
        difficulty = o.get("difficulty")
        if difficulty is not None:
            difficulty = self.string(difficulty, p + "difficulty", DIFFICULTY_NAMES)
        attrs = o.get("source_attributes", {})
        if not isinstance(attrs, dict):
            raise self.fail(p + "source_attributes", "expected an object")
        track = self.schema2_keys(o, SCHEMA2_OBJECT_FIELDS, p)
        track_id, velocity = track["track_id"], track["velocity"]
        return ObjectRecord(
            category=category, instance_id=instance_id, box=Box3D(center, dims, rotation),
            keypoints=keypoints, in_image=in_image, behind_camera=behind, occluded=occluded, bbox=bbox,
            truncation=truncation, occlusion=occlusion, occlusion_level=level,
            bbox_source=None if bbox_source is None else self.box2d(bbox_source, p + "bbox_source"),
            bbox_visible=None if bbox_visible is None else self.box2d(bbox_visible, p + "bbox_visible"),
            difficulty=difficulty, source_attributes=attrs,
            track_id=None if track_id is None else self.integer(track_id, p + "track_id", 1, _TRACK_ID_MAX),
            velocity=None if velocity is None else self.array(velocity, p + "velocity", (3,)),
        )
