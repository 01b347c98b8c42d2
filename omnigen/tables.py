"""The columnar tables of a dataset: one row per object (ObjectTable), one per frame (FrameTable).

Why columns: statistics, exports and training read a whole dataset at once, and a column per field
turns a pass over 100,000 ObjectRecords into a few vectorised array operations. The tables are
what the index (.index.npz, omnigen.index) stores and what a Dataset (omnigen.dataset) reads
records back from; they know nothing of files.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from omnigen.conventions import CLASS_INDEX, FINE_CLASSES, NUM_KEYPOINTS
from omnigen.record import DIFFICULTY_NAMES, FrameRecord

_OBJECT_COLUMNS = {
    # name: (dtype, per-object shape, fill for "absent")
    "frame": (np.int32, (), -1),
    "category": (np.int16, (), -1),
    "instance_id": (np.int32, (), 0),
    "center": (np.float64, (3,), np.nan),
    "dims": (np.float64, (3,), np.nan),
    "rotation": (np.float64, (3, 3), np.nan),
    "keypoints": (np.float64, (NUM_KEYPOINTS, 2), np.nan),
    "in_image": (np.bool_, (NUM_KEYPOINTS,), False),
    "behind_camera": (np.bool_, (NUM_KEYPOINTS,), False),
    "occluded": (np.bool_, (NUM_KEYPOINTS,), False),
    "bbox": (np.float64, (4,), np.nan),
    "bbox_source": (np.float64, (4,), np.nan),
    "bbox_visible": (np.float64, (4,), np.nan),
    "truncation": (np.float64, (), np.nan),
    "occlusion": (np.float64, (), np.nan),
    "occlusion_level": (np.int8, (), 3),
    "difficulty": (np.int8, (), -1),
    "track_id": (np.int64, (), -1),
    "velocity": (np.float64, (3,), np.nan),
}


@dataclass
class ObjectTable:
    """Every object of a dataset as parallel arrays (one row per object), for fast statistics.

    `frame` is the row's frame index; `category` indexes FINE_CLASSES; absent optional boxes,
    occlusion and world velocities are NaN; `difficulty` indexes DIFFICULTY_NAMES, -1 where
    undefined; `track_id` is -1 where the object has none.
    """

    frame: np.ndarray
    category: np.ndarray
    instance_id: np.ndarray
    center: np.ndarray
    dims: np.ndarray
    rotation: np.ndarray
    keypoints: np.ndarray
    in_image: np.ndarray
    behind_camera: np.ndarray
    occluded: np.ndarray
    bbox: np.ndarray
    bbox_source: np.ndarray
    bbox_visible: np.ndarray
    truncation: np.ndarray
    occlusion: np.ndarray
    occlusion_level: np.ndarray
    difficulty: np.ndarray
    track_id: np.ndarray
    velocity: np.ndarray

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def category_names(self) -> np.ndarray:
        return np.asarray(FINE_CLASSES, dtype=object)[self.category]

    @classmethod
    def from_records(cls, records: Iterable[FrameRecord]) -> "ObjectTable":
        rows: dict[str, list] = {name: [] for name in _OBJECT_COLUMNS}
        no_box = np.full(4, np.nan)  # an absent bbox_source / bbox_visible: one shared row of NaN
        no_velocity = np.full(3, np.nan)
        for f_index, rec in enumerate(records):
            for o in rec.objects:
                rows["frame"].append(f_index)
                rows["category"].append(CLASS_INDEX[o.category])
                rows["instance_id"].append(o.instance_id)
                rows["center"].append(o.box.center)
                rows["dims"].append(o.box.dims)
                rows["rotation"].append(o.box.rotation)
                rows["keypoints"].append(o.keypoints)
                rows["in_image"].append(o.in_image)
                rows["behind_camera"].append(o.behind_camera)
                rows["occluded"].append(o.occluded)
                rows["bbox"].append(o.bbox)
                rows["bbox_source"].append(o.bbox_source if o.bbox_source is not None else no_box)
                rows["bbox_visible"].append(o.bbox_visible if o.bbox_visible is not None else no_box)
                rows["truncation"].append(o.truncation)
                rows["occlusion"].append(np.nan if o.occlusion is None else o.occlusion)
                rows["occlusion_level"].append(o.occlusion_level)
                rows["difficulty"].append(-1 if o.difficulty is None else DIFFICULTY_NAMES.index(o.difficulty))
                rows["track_id"].append(-1 if o.track_id is None else o.track_id)
                rows["velocity"].append(no_velocity if o.velocity is None else o.velocity)
        columns = {}
        for name, (dtype, shape, fill) in _OBJECT_COLUMNS.items():
            values = rows[name]
            if not values:
                columns[name] = np.zeros((0, *shape), dtype=dtype)
            else:
                columns[name] = np.asarray(values, dtype=dtype).reshape(len(values), *shape)
        return cls(**columns)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The columns as the index stores them (obj_<name>), in column order."""
        return {f"obj_{name}": getattr(self, name) for name in _OBJECT_COLUMNS}

    @classmethod
    def from_arrays(cls, z: Any) -> "ObjectTable":
        """The table from the index's arrays (an opened .npz or a dict like to_arrays')."""
        return cls(**{name: z[f"obj_{name}"] for name in _OBJECT_COLUMNS})

    @classmethod
    def concat(cls, tables: list["ObjectTable"], frame_offsets: list[int]) -> "ObjectTable":
        """Stack tables; each table's `frame` column is shifted by its frame offset."""
        cols = {name: np.concatenate([getattr(t, name) for t in tables]) for name in _OBJECT_COLUMNS}
        cols["frame"] = np.concatenate([t.frame + off for t, off in zip(tables, frame_offsets)]).astype(np.int32)
        return cls(**cols)

    def take(self, rows: np.ndarray) -> "ObjectTable":
        return ObjectTable(**{name: getattr(self, name)[rows] for name in _OBJECT_COLUMNS})


_FRAME_STRINGS = ("frame_id", "source", "view", "image", "group", "sequence", "pair")
_FRAME_ARRAYS = ("width", "height", "K", "ground_plane", "camera_height", "camera_pitch", "schema_version",
                 "timestamp", "camera_to_world")


@dataclass
class FrameTable:
    """Every frame's own fields as columns: strings as lists, numbers as arrays.

    Absent ground planes, camera heights and pitches, timestamps and camera_to_world are NaN;
    absent groups, sequences and pairs None. The nested, rarely needed fields
    (synthetic info, ignore regions) stay a JSON blob until first asked for.
    """

    frame_id: list[str]
    source: list[str]
    view: list[str]
    image: list[str]
    group: list[str | None]
    sequence: list[str | None]
    pair: list[str | None]
    width: np.ndarray
    height: np.ndarray
    K: np.ndarray  # (F, 3, 3)
    ground_plane: np.ndarray  # (F, 4): normal, offset
    camera_height: np.ndarray
    camera_pitch: np.ndarray
    schema_version: np.ndarray
    timestamp: np.ndarray
    camera_to_world: np.ndarray  # (F, 4, 4)
    extras_blob: bytes = b"[]"
    _extras: list[dict[str, Any]] | None = None

    def __len__(self) -> int:
        return len(self.frame_id)

    @property
    def extras(self) -> list[dict[str, Any]]:
        """Per frame {"synthetic": ..., "ignore_regions": [...]}, parsed on first use."""
        if self._extras is None:
            self._extras = json.loads(self.extras_blob)
        return self._extras

    @classmethod
    def from_records(cls, records: list[FrameRecord]) -> "FrameTable":
        n = len(records)
        plane = np.full((n, 4), np.nan)
        for i, r in enumerate(records):
            if r.ground_plane is not None:
                plane[i] = [*r.ground_plane.normal, r.ground_plane.offset]
        extras = [{"synthetic": None if r.synthetic is None else r.synthetic.to_dict(),
                   "ignore_regions": [g.to_dict() for g in r.ignore_regions]} for r in records]
        return cls(
            frame_id=[r.frame_id for r in records], source=[r.source for r in records],
            view=[r.view for r in records], image=[r.image for r in records], group=[r.group for r in records],
            sequence=[r.sequence for r in records], pair=[r.pair for r in records],
            width=np.array([r.width for r in records], dtype=np.int32),
            height=np.array([r.height for r in records], dtype=np.int32),
            K=np.array([r.K for r in records], dtype=np.float64).reshape(n, 3, 3), ground_plane=plane,
            camera_height=np.array([np.nan if r.camera_height is None else r.camera_height for r in records], dtype=np.float64),
            camera_pitch=np.array([np.nan if r.camera_pitch is None else r.camera_pitch for r in records], dtype=np.float64),
            schema_version=np.array([r.schema_version for r in records], dtype=np.int16),
            timestamp=np.array([np.nan if r.timestamp is None else r.timestamp for r in records], dtype=np.float64),
            camera_to_world=np.array([_NO_POSE if r.camera_to_world is None else r.camera_to_world for r in records],
                                     dtype=np.float64).reshape(n, 4, 4),
            extras_blob=json.dumps(extras).encode(),
        )

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The columns as the index stores them: frm_<name>, strings and extras as JSON bytes."""
        strings = {name: getattr(self, name) for name in _FRAME_STRINGS}
        return {
            "frm_strings": np.frombuffer(json.dumps(strings).encode(), dtype=np.uint8),
            "frm_extras": np.frombuffer(self.extras_blob, dtype=np.uint8),
            **{f"frm_{k}": getattr(self, k) for k in _FRAME_ARRAYS},
        }

    @classmethod
    def from_arrays(cls, z: Any) -> "FrameTable":
        strings = json.loads(z["frm_strings"].tobytes())
        return cls(**strings, **{k: z[f"frm_{k}"] for k in _FRAME_ARRAYS},
                   extras_blob=z["frm_extras"].tobytes())

    @classmethod
    def concat(cls, tables: list["FrameTable"]) -> "FrameTable":
        extras = [e for t in tables for e in t.extras]
        return cls(**{k: [v for t in tables for v in getattr(t, k)] for k in _FRAME_STRINGS},
                   **{k: np.concatenate([getattr(t, k) for t in tables]) for k in _FRAME_ARRAYS},
                   extras_blob=json.dumps(extras).encode(), _extras=extras)

    def take(self, rows: list[int] | np.ndarray) -> "FrameTable":
        rows = [int(r) for r in rows]
        extras = [self.extras[r] for r in rows]
        return FrameTable(**{k: [getattr(self, k)[r] for r in rows] for k in _FRAME_STRINGS},
                          **{k: getattr(self, k)[rows] for k in _FRAME_ARRAYS},
                          extras_blob=json.dumps(extras).encode(), _extras=extras)

    def row(self, i: int) -> dict[str, Any]:
        """Frame i's fields as in its record (without objects)."""
        gp = self.ground_plane[i]
        return {
            "schema_version": int(self.schema_version[i]), "frame_id": self.frame_id[i], "source": self.source[i],
            "view": self.view[i], "image": self.image[i], "width": int(self.width[i]), "height": int(self.height[i]),
            "K": self.K[i].tolist(),
            "ground_plane": None if np.isnan(gp).any() else {"normal": gp[:3].tolist(), "offset": float(gp[3])},
            "camera_height": _nan_to_none(self.camera_height[i]), "camera_pitch": _nan_to_none(self.camera_pitch[i]),
            "group": self.group[i], "sequence": self.sequence[i], "timestamp": _nan_to_none(self.timestamp[i]),
            "pair": self.pair[i], "camera_to_world": _nan_to_none_array(self.camera_to_world[i]),
            **self.extras[i],
        }


_NO_POSE = np.full((4, 4), np.nan)


def _nan_to_none(v: float) -> float | None:
    return None if np.isnan(v) else float(v)


def _nan_to_none_array(a: np.ndarray) -> list | None:
    return None if np.isnan(a).any() else a.tolist()
