"""An UrbanOmniView dataset folder: reading, writing and the columnar index.

Layout (docs/dataset-format.md):

    DATASET/
      manifest.json          what the dataset holds (counts, sources, hashes, omnigen version)
      records/<frame_id>.json  one validated record per frame: the source of truth
      images/ depth/ instance/ the pixels, named by frame id (linked, not copied, where possible)
      .index.npz             a columnar cache of all records, rebuilt when records/ changes

Why per-frame records: renders and conversions write frames one at a time, from many processes,
and resume after an interruption by skipping frames whose record exists; a per-frame file written
atomically makes each of these safe. Why an index: parsing 40,000 JSON files costs tens of
seconds, while reading one .npz with the same content costs a fraction of one. The index stores a
fingerprint of records/ (names, sizes, modification times) and is rebuilt when it no longer matches.
A dataset that cannot be written (a read-only mount, a copy without write permission) gets the
rebuilt index in memory for the run, and a one-line note says so.

Consumers find a frame's record by its file name (records/<frame_id>.json), so opening refuses a
record whose frame_id is not its file name: read by id, it would be missed, doubled or mixed up.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import sys
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from omnigen import __version__
from omnigen.conventions import CLASS_INDEX, FINE_CLASSES, NUM_KEYPOINTS, SCHEMA_VERSION
from omnigen.files import TMP_PREFIX, atomic_write_bytes, atomic_write_json, dumps_json
from omnigen.geometry import Box3D, Plane
from omnigen.progress import progress
from omnigen.record import DIFFICULTY_NAMES, FrameRecord, IgnoreRegion, ObjectRecord, RecordError, SyntheticInfo

MANIFEST = "manifest.json"
RECORDS_DIR = "records"
INDEX_FILE = ".index.npz"
RENDER_ARGS_FILE = ".render-args.json"  # a render folder's recorded arguments (rigs/render.py)
INDEX_VERSION = 2
FORMAT_NAME = "UrbanOmniView"


class DatasetError(RuntimeError):
    """A dataset folder that cannot be read as a whole (missing, or with bad records)."""


# ---------------------------------------------------------------------------------------------
# The columnar object table
# ---------------------------------------------------------------------------------------------

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
}


@dataclass
class ObjectTable:
    """Every object of a dataset as parallel arrays (one row per object), for fast statistics.

    `frame` is the row's frame index; `category` indexes FINE_CLASSES; absent optional boxes
    and occlusion are NaN; `difficulty` indexes DIFFICULTY_NAMES, -1 where undefined.
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

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def category_names(self) -> np.ndarray:
        return np.asarray(FINE_CLASSES, dtype=object)[self.category]

    @classmethod
    def from_records(cls, records: Iterable[FrameRecord]) -> "ObjectTable":
        rows: dict[str, list] = {name: [] for name in _OBJECT_COLUMNS}
        no_box = np.full(4, np.nan)  # an absent bbox_source / bbox_visible: one shared row of NaN
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
        columns = {}
        for name, (dtype, shape, fill) in _OBJECT_COLUMNS.items():
            values = rows[name]
            if not values:
                columns[name] = np.zeros((0, *shape), dtype=dtype)
            else:
                columns[name] = np.asarray(values, dtype=dtype).reshape(len(values), *shape)
        return cls(**columns)

    def columns(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in _OBJECT_COLUMNS}

    @classmethod
    def concat(cls, tables: list["ObjectTable"], frame_offsets: list[int]) -> "ObjectTable":
        """Stack tables; each table's `frame` column is shifted by its frame offset."""
        cols = {name: np.concatenate([getattr(t, name) for t in tables]) for name in _OBJECT_COLUMNS}
        cols["frame"] = np.concatenate([t.frame + off for t, off in zip(tables, frame_offsets)]).astype(np.int32)
        return cls(**cols)

    def take(self, rows: np.ndarray) -> "ObjectTable":
        return ObjectTable(**{name: getattr(self, name)[rows] for name in _OBJECT_COLUMNS})


# ---------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------


def record_path(root: Path, frame_id: str) -> Path:
    return Path(root) / RECORDS_DIR / f"{frame_id}.json"


def record_files(root: Path) -> list[os.DirEntry]:
    """The finished record files of a dataset, in frame-id order (temporary files skipped)."""
    folder = Path(root) / RECORDS_DIR
    if not folder.is_dir():
        return []
    with os.scandir(folder) as it:
        entries = [e for e in it if e.name.endswith(".json") and not e.name.startswith(TMP_PREFIX)]
    entries.sort(key=lambda e: e.name[:-5])  # frame-id order, the order of the index and the digest
    return entries


def records_fingerprint(entries: list[os.DirEntry]) -> str:
    """Cheap identity of records/: names, sizes and modification times of every record file."""
    h = hashlib.sha256()
    for e in entries:
        st = e.stat()
        h.update(f"{e.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def update_records_digest(digest: "hashlib._Hash", name: str, data: bytes) -> None:
    """Fold one record file into the dataset's records_sha256 (name and bytes, in frame-id order)."""
    digest.update(name.encode() + b"\0" + data)


def check_record_name(frame_id: str, file_name: str, path: str | os.PathLike) -> None:
    """A record must be filed as records/<its frame_id>.json; anything else is refused by name."""
    if file_name != f"{frame_id}.json":
        raise DatasetError(f"{path}: frame_id: {frame_id!r} does not match the file name {file_name!r}; records are "
                           "found by file name, so the dataset is refused (omnigen validate lists every such record)")


def read_record(path: str | os.PathLike) -> FrameRecord:
    """Read and validate one record file; errors name the file."""
    path = str(path)
    try:
        with open(path, "rb") as fh:
            data = json.loads(fh.read())
    except json.JSONDecodeError as exc:
        raise RecordError(None, "<json>", f"not valid JSON: {exc}", path) from None
    return FrameRecord.from_dict(data, file=path)


_FRAME_STRINGS = ("frame_id", "source", "view", "image", "group")
_FRAME_ARRAYS = ("width", "height", "K", "ground_plane", "camera_height", "camera_pitch", "schema_version")


@dataclass
class FrameTable:
    """Every frame's own fields as columns: strings as lists, numbers as arrays.

    Absent ground planes, camera heights and pitches are NaN. The nested, rarely needed fields
    (synthetic info, ignore regions) stay a JSON blob until first asked for.
    """

    frame_id: list[str]
    source: list[str]
    view: list[str]
    image: list[str]
    group: list[str | None]
    width: np.ndarray
    height: np.ndarray
    K: np.ndarray  # (F, 3, 3)
    ground_plane: np.ndarray  # (F, 4): normal, offset
    camera_height: np.ndarray
    camera_pitch: np.ndarray
    schema_version: np.ndarray
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
            width=np.array([r.width for r in records], dtype=np.int32),
            height=np.array([r.height for r in records], dtype=np.int32),
            K=np.array([r.K for r in records], dtype=np.float64).reshape(n, 3, 3), ground_plane=plane,
            camera_height=np.array([np.nan if r.camera_height is None else r.camera_height for r in records], dtype=np.float64),
            camera_pitch=np.array([np.nan if r.camera_pitch is None else r.camera_pitch for r in records], dtype=np.float64),
            schema_version=np.array([r.schema_version for r in records], dtype=np.int16),
            extras_blob=json.dumps(extras).encode(),
        )

    def to_arrays(self) -> dict[str, np.ndarray]:
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
            "group": self.group[i], **self.extras[i],
        }


def _nan_to_none(v: float) -> float | None:
    return None if np.isnan(v) else float(v)


class Dataset:
    """A dataset opened for reading: the frame table, the object table, the manifest.

    `ds[i]` builds the i-th FrameRecord on demand from the index; `ds.table` (frames) and
    `ds.objects` (objects) are columns for vectorised work over a whole dataset at once.
    """

    def __init__(self, root: Path, table: FrameTable, offsets: np.ndarray, objects: ObjectTable,
                 attributes_blob: bytes | None, manifest: dict[str, Any]):
        self.root = Path(root)
        self.table = table
        self.offsets = offsets
        self.objects = objects
        self._attributes_blob = attributes_blob
        self._attributes: list[dict[str, Any]] | None = None
        self.manifest = manifest
        self._by_id: dict[str, int] | None = None
        self._frames: list[dict[str, Any]] | None = None

    # -- opening ------------------------------------------------------------------------------
    @classmethod
    def open(cls, root: str | os.PathLike, rebuild: bool = False, show_progress: bool = True) -> "Dataset":
        """Open a dataset folder, rebuilding the index if records/ changed since it was written."""
        root = Path(root)
        if not (root / RECORDS_DIR).is_dir():
            raise DatasetError(f"{root}: not an UrbanOmniView dataset (no {RECORDS_DIR}/ folder)")
        entries = record_files(root)
        key = records_fingerprint(entries)
        manifest = read_manifest(root)
        if not rebuild:
            loaded = _load_index(root, key, manifest)
            # an index from before the name check could hold a record filed under another id
            if loaded is not None and loaded.table.frame_id == [e.name[:-5] for e in entries]:
                return loaded
        records = []
        for e in progress(entries, desc="reading records", disable=not show_progress):
            records.append(read_record(e.path))
            check_record_name(records[-1].frame_id, e.name, e.path)
        return build_index(root, records, key, manifest, cache=True)

    # -- access -------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.table)

    def __iter__(self) -> Iterator[FrameRecord]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, i: int) -> FrameRecord:
        lo, hi = int(self.offsets[i]), int(self.offsets[i + 1])
        return _frame_from_row(self.table.row(i), [self._object(j) for j in range(lo, hi)])

    @property
    def frames(self) -> list[dict[str, Any]]:
        """Every frame's fields as dicts (built on first use; prefer `table` in hot loops)."""
        if self._frames is None:
            self._frames = [self.table.row(i) for i in range(len(self))]
        return self._frames

    @property
    def frame_ids(self) -> list[str]:
        return self.table.frame_id

    def index_of(self, frame_id: str) -> int:
        if self._by_id is None:
            self._by_id = {f: i for i, f in enumerate(self.table.frame_id)}
        try:
            return self._by_id[frame_id]
        except KeyError:
            raise KeyError(f"{self.root}: no frame {frame_id!r}") from None

    def frame(self, frame_id: str) -> FrameRecord:
        return self[self.index_of(frame_id)]

    def path(self, relative: str) -> Path:
        """Absolute path of a file named in a record (image, depth, instance)."""
        return self.root / relative

    @property
    def source_attributes(self) -> list[dict[str, Any]]:
        """Per-object source attributes, parsed on first use (most consumers never need them)."""
        if self._attributes is None:
            self._attributes = json.loads(self._attributes_blob) if self._attributes_blob else []
        return self._attributes

    def _object(self, j: int) -> ObjectRecord:
        t = self.objects
        src, vis = t.bbox_source[j], t.bbox_visible[j]
        occ = t.occlusion[j]
        diff = int(t.difficulty[j])
        return ObjectRecord(
            category=FINE_CLASSES[t.category[j]], instance_id=int(t.instance_id[j]),
            box=Box3D(t.center[j], t.dims[j], t.rotation[j]), keypoints=t.keypoints[j].copy(),
            in_image=t.in_image[j].copy(), behind_camera=t.behind_camera[j].copy(), occluded=t.occluded[j].copy(),
            bbox=t.bbox[j].copy(), truncation=float(t.truncation[j]),
            occlusion=None if np.isnan(occ) else float(occ), occlusion_level=int(t.occlusion_level[j]),
            bbox_source=None if np.isnan(src).any() else src.copy(),
            bbox_visible=None if np.isnan(vis).any() else vis.copy(),
            difficulty=None if diff < 0 else DIFFICULTY_NAMES[diff],
            source_attributes=self.source_attributes[j] if self._attributes_blob else {},
        )


def _frame_from_row(f: dict[str, Any], objects: list[ObjectRecord]) -> FrameRecord:
    gp = f["ground_plane"]
    syn = f["synthetic"]
    return FrameRecord(
        frame_id=f["frame_id"], source=f["source"], view=f["view"], image=f["image"], width=f["width"],
        height=f["height"], K=np.asarray(f["K"], dtype=np.float64), objects=objects,
        ignore_regions=[IgnoreRegion(np.asarray(r["bbox"], dtype=np.float64), r["label"]) for r in f["ignore_regions"]],
        ground_plane=None if gp is None else Plane(gp["normal"], gp["offset"]),
        camera_height=f["camera_height"], camera_pitch=f["camera_pitch"], group=f["group"],
        synthetic=None if syn is None else SyntheticInfo(**syn), schema_version=f["schema_version"],
    )


def read_manifest(root: Path) -> dict[str, Any]:
    """A dataset folder's manifest.json, {} when it has none; a manifest that is no JSON is an error."""
    path = root / MANIFEST
    if not path.exists():
        return {}
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: not valid JSON: {exc}") from None


def _load_index(root: Path, key: str, manifest: dict[str, Any]) -> Dataset | None:
    path = root / INDEX_FILE
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            header = json.loads(z["header"].tobytes())
            if header.get("version") != INDEX_VERSION or header.get("key") != key:
                return None
            table = FrameTable.from_arrays(z)
            offsets = z["offsets"]
            objects = ObjectTable(**{name: z[f"obj_{name}"] for name in _OBJECT_COLUMNS})
            attributes = z["attributes"].tobytes() if "attributes" in z.files else None
    except (OSError, ValueError, KeyError):
        return None  # unreadable or foreign cache: rebuild it
    return Dataset(root, table, offsets, objects, attributes, manifest)


@dataclass
class IndexRows:
    """One frame's share of the index: the frame without its objects, its objects as columns.

    Why not the record itself: a forked converter worker sends one of these back per frame, and
    a few stacked arrays pickle in a fifth of the time of a list of ObjectRecords; stacking
    12,000 of them at the end is one concatenate per column instead of a pass over 100,000
    objects.
    """

    frame: FrameRecord  # with objects=[]
    objects: ObjectTable  # its `frame` column is 0
    attributes: list[dict[str, Any]]  # each object's source_attributes

    @classmethod
    def of(cls, record: FrameRecord) -> "IndexRows":
        return cls(replace(record, objects=[]), ObjectTable.from_records([record]),
                   [o.source_attributes for o in record.objects])

    @property
    def frame_id(self) -> str:
        return self.frame.frame_id


def build_index(root: Path, records: list[FrameRecord], key: str | None = None,
                manifest: dict[str, Any] | None = None, cache: bool = False) -> Dataset:
    """Write the columnar index of `records` and return the opened dataset (see write_index for `cache`)."""
    return index_from_rows(root, [IndexRows.of(r) for r in records], key, manifest, cache)


def index_from_rows(root: Path, rows: list[IndexRows], key: str | None = None,
                    manifest: dict[str, Any] | None = None, cache: bool = False) -> Dataset:
    """Write the index of frames given as IndexRows (sorted here by frame id); return the dataset."""
    rows = sorted(rows, key=lambda r: r.frame_id)
    counts = [len(r.objects) for r in rows]
    attributes = [a for r in rows for a in r.attributes]
    objects = (ObjectTable.concat([r.objects for r in rows], list(range(len(rows)))) if rows
               else ObjectTable.from_records([]))
    return write_index(
        root, FrameTable.from_records([r.frame for r in rows]),
        np.cumsum([0] + counts).astype(np.int64), objects,
        attributes if any(attributes) else None, key, manifest, cache,
    )


def write_index(root: str | os.PathLike, table: FrameTable, offsets: np.ndarray, objects: ObjectTable,
                attributes: list[dict[str, Any]] | None, key: str | None = None,
                manifest: dict[str, Any] | None = None, cache: bool = False) -> Dataset:
    """Write the index from columns (frames sorted by id) and return the opened dataset.

    `key` is the fingerprint of records/ the index describes; by default, that of the folder now.
    `cache`: the index is only a reader's cache, so a folder that cannot be written (read-only
    file system, no permission) keeps it in memory, with one line on stderr; a job that writes the
    dataset (a merge, a finalize) passes False and fails instead.
    """
    root = Path(root)
    if key is None:
        key = records_fingerprint(record_files(root))
    attributes_blob = json.dumps(attributes).encode() if attributes else None
    arrays = {f"obj_{k}": v for k, v in objects.columns().items()}
    arrays.update(table.to_arrays())
    arrays["header"] = np.frombuffer(json.dumps({"version": INDEX_VERSION, "key": key}).encode(), dtype=np.uint8)
    arrays["offsets"] = offsets
    if attributes_blob is not None:
        arrays["attributes"] = np.frombuffer(attributes_blob, dtype=np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    try:
        atomic_write_bytes(root / INDEX_FILE, buf.getvalue())
    except OSError as exc:
        if not cache or exc.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
            raise
        print(f"{root}: cannot write {INDEX_FILE} ({os.strerror(exc.errno)}); using an index built in memory "
              f"for this run ({len(table)} frames)", file=sys.stderr)
    return Dataset(root, table, offsets, objects, attributes_blob, manifest if manifest is not None else read_manifest(root))


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------


class DatasetWriter:
    """Writes a dataset frame by frame; safe to resume and to share between processes.

    Each record is written atomically to records/<frame_id>.json. `has()` lets a resumed job skip
    finished frames. `finalize()` (run once, after all writers are done) builds the index and
    the manifest from whatever records/ holds.
    """

    def __init__(self, root: str | os.PathLike, durable: bool = True):
        self.root = Path(root)
        (self.root / RECORDS_DIR).mkdir(parents=True, exist_ok=True)
        self.durable = durable
        self.keep_written = True
        """Remember written frames so finalize indexes them from memory; a writer in a worker
        process turns this off and its parent `adopt`s the IndexRows each write returns."""
        self._written: dict[str, IndexRows] = {}

    def has(self, frame_id: str) -> bool:
        return record_path(self.root, frame_id).exists()

    def write(self, record: FrameRecord) -> IndexRows:
        """Validate and write one record atomically; returns what the index needs of it.

        The dict that is dumped is the dict that is validated (the same check as parsing the
        dumped text back, without the cost of the parse).
        """
        d = record.to_dict()
        path = record_path(self.root, record.frame_id)
        FrameRecord.from_dict(d, file=str(path))
        atomic_write_bytes(path, dumps_json(d).encode(), durable=self.durable)
        rows = IndexRows.of(record)
        if self.keep_written:
            self._written[record.frame_id] = rows
        return rows

    def adopt(self, rows: IndexRows) -> None:
        """Index a frame that another process wrote (and validated) from memory."""
        self._written[rows.frame_id] = rows

    def drop_unwritten(self) -> list[str]:
        """Delete the records this writer neither wrote nor adopted, and their images; their ids.

        For jobs that rewrite a whole dataset (a conversion): a record an earlier run left, of a
        frame now skipped or past --limit, would otherwise be indexed as if this run had made it.
        The record goes first, so a kill in between leaves an unused image, never a record
        without its image.
        """
        dropped = []
        for e in record_files(self.root):
            frame_id = e.name[:-5]
            if frame_id in self._written:
                continue
            try:
                image = json.loads(Path(e.path).read_bytes()).get("image")
            except (json.JSONDecodeError, UnicodeDecodeError, AttributeError):
                image = None
            Path(e.path).unlink()
            parts = Path(image).parts if isinstance(image, str) else ()
            if len(parts) == 2 and parts[0] == "images":  # nothing outside the dataset's images/
                (self.root / image).unlink(missing_ok=True)
            dropped.append(frame_id)
        return dropped

    def finalize(self, extra: dict[str, Any] | None = None, show_progress: bool = True) -> Dataset:
        """Index every record in records/ and write manifest.json; returns the opened dataset."""
        entries = record_files(self.root)
        key = records_fingerprint(entries)
        rows = []
        digest = hashlib.sha256()
        for e in progress(entries, desc="indexing", disable=not show_progress):
            data = Path(e.path).read_bytes()
            update_records_digest(digest, e.name, data)
            frame_id = e.name[:-5]
            cached = self._written.get(frame_id)
            if cached is not None:
                rows.append(cached)
            else:
                try:
                    rows.append(IndexRows.of(FrameRecord.from_dict(json.loads(data), file=e.path)))
                except json.JSONDecodeError as exc:
                    raise RecordError(frame_id, "<json>", f"not valid JSON: {exc}", e.path) from None
                check_record_name(rows[-1].frame_id, e.name, e.path)
        ds = index_from_rows(self.root, rows, key, manifest={})
        ds.manifest = make_manifest(ds, digest.hexdigest(), extra or {})
        atomic_write_json(self.root / MANIFEST, ds.manifest, indent=2)  # last: it seals the dataset
        return ds


def make_manifest(ds: Dataset, records_sha256: str, extra: dict[str, Any]) -> dict[str, Any]:
    """The manifest: what a dataset holds, with no timestamps, so equal inputs give equal bytes."""
    by_class = Counter(np.asarray(FINE_CLASSES)[ds.objects.category].tolist())
    manifest = {
        "format": FORMAT_NAME,
        "schema_version": SCHEMA_VERSION,
        "omnigen_version": __version__,
        "records_sha256": records_sha256,
        "counts": {
            "frames": len(ds),
            "objects": len(ds.objects),
            "frames_by_source": dict(sorted(Counter(ds.table.source).items())),
            "frames_by_view": dict(sorted(Counter(ds.table.view).items())),
            "objects_by_class": dict(sorted(by_class.items())),
        },
    }
    manifest.update(extra)
    return manifest
