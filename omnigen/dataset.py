"""An UrbanOmniView dataset folder: its layout, its records, and the Dataset that reads it.

Layout (docs/dataset-format.md):

    DATASET/
      manifest.json          what the dataset holds (counts, sources, hashes, omnigen version)
      records/<frame_id>.json  one validated record per frame: the source of truth
      images/ depth/ instance/ the pixels, named by frame id (linked, not copied, where possible)
      .index.npz             a columnar cache of all records, rebuilt when records/ changes

Why per-frame records: renders and conversions write frames one at a time, from many processes,
and resume after an interruption by skipping frames whose record exists; a per-frame file written
atomically makes each of these safe. Reading goes through the index (omnigen.index), the records'
content as columns (omnigen.tables), rebuilt here when it no longer matches records/. A dataset
that cannot be written (a read-only mount, a copy without write permission) gets the rebuilt
index in memory for the run, and a one-line note says so. Writing is omnigen.writer's.

Consumers find a frame's record by its file name (records/<frame_id>.json), so opening refuses a
record whose frame_id is not its file name: read by id, it would be missed, doubled or mixed up.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from omnigen.conventions import FINE_CLASSES
from omnigen.files import TMP_PREFIX
from omnigen.geometry import Box3D, Plane
from omnigen.index import DatasetIndex, read_index, records_fingerprint, write_index
from omnigen.options import SEED_MAX
from omnigen.progress import progress
from omnigen.record import DIFFICULTY_NAMES, FrameRecord, IgnoreRegion, ObjectRecord, RecordError, SyntheticInfo
from omnigen.tables import FrameTable, ObjectTable
from omnigen.taxonomy import TaxonomyError, recorded_taxonomy
from omnigen.untrusted import UntrustedFileError, read_regular

MANIFEST = "manifest.json"
MANIFEST_MAX_BYTES = 16 * 2**20
"""Largest manifest.json read. A manifest holds counts, a merge's sources and its splits' counts:
kilobytes, tens for a merge of many sources; the cap only keeps a huge or endless file out."""
RECORDS_DIR = "records"
RECORD_MAX_BYTES = 64 * 2**20
"""Largest record file read. A record holds one frame's objects, about 1.5 kB each: a frame of
40,000 objects fits; the cap only keeps a huge or endless file out."""
RENDER_ARGS_FILE = ".render-args.json"  # a render folder's recorded arguments (rigs/render.py)


class DatasetError(RuntimeError):
    """A dataset folder that cannot be read as a whole (missing, or with bad records)."""


class ManifestError(DatasetError):
    """A manifest.json that is unreadable or breaks its schema; names the file and the field."""

    def __init__(self, file: str | os.PathLike, field: str, message: str):
        self.file, self.field, self.message = os.fspath(file), field, message
        super().__init__(f"{self.file}: field '{field}': {message}")


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


def check_record_name(frame_id: str, file_name: str, path: str | os.PathLike) -> None:
    """A record must be filed as records/<its frame_id>.json; anything else is refused by name."""
    if file_name != f"{frame_id}.json":
        raise DatasetError(f"{path}: frame_id: {frame_id!r} does not match the file name {file_name!r}; records are "
                           "found by file name, so the dataset is refused (omnigen validate lists every such record)")


def read_record_bytes(path: str | os.PathLike) -> bytes:
    """A record file's bytes, read as a regular file of at most RECORD_MAX_BYTES (a record named
    like one but replaced by a FIFO or a link to a device would block or fill memory)."""
    try:
        return read_regular(path, RECORD_MAX_BYTES)
    except UntrustedFileError as exc:
        raise RecordError(None, "<file>", exc.message, os.fspath(path)) from None


def parse_record(data: bytes, path: str | os.PathLike) -> FrameRecord:
    """Parse and validate one record file's bytes; errors name the file."""
    try:
        parsed = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RecordError(None, "<json>", f"not valid JSON: {exc}", os.fspath(path)) from None
    except RecursionError:
        raise RecordError(None, "<json>", "JSON nested too deeply to read", os.fspath(path)) from None
    return FrameRecord.from_dict(parsed, file=os.fspath(path))


def read_record(path: str | os.PathLike) -> FrameRecord:
    """Read and validate one record file; errors name the file."""
    return parse_record(read_record_bytes(path), path)


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
            index = read_index(root, key)
            # an index from before the name check could hold a record filed under another id
            if index is not None and index.table.frame_id == [e.name[:-5] for e in entries]:
                return cls.from_index(root, index, manifest)
        records = []
        for e in progress(entries, desc="reading records", disable=not show_progress):
            records.append(read_record(e.path))
            check_record_name(records[-1].frame_id, e.name, e.path)
        index = DatasetIndex.from_records(records)
        write_index(root, index, key, cache=True)
        return cls.from_index(root, index, manifest)

    @classmethod
    def from_index(cls, root: str | os.PathLike, index: DatasetIndex, manifest: dict[str, Any]) -> "Dataset":
        """The dataset whose records `index` holds (as read or just written; nothing is checked here)."""
        return cls(root, index.table, index.offsets, index.objects, index.attributes_blob, manifest)

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
    def has_source_attributes(self) -> bool:
        """Whether the index holds source attributes (it holds none when every object's is empty)."""
        return bool(self._attributes_blob)

    @property
    def source_attributes(self) -> list[dict[str, Any]]:
        """Per-object source attributes, parsed on first use (most consumers never need them);
        [] when the index holds none (has_source_attributes)."""
        if self._attributes is None:
            self._attributes = json.loads(self._attributes_blob) if self._attributes_blob else []
        return self._attributes

    def _object(self, j: int) -> ObjectRecord:
        t = self.objects
        src, vis = t.bbox_source[j], t.bbox_visible[j]
        occ = t.occlusion[j]
        diff = int(t.difficulty[j])
        track, velocity = int(t.track_id[j]), t.velocity[j]
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
            track_id=None if track < 0 else track, velocity=None if np.isnan(velocity).any() else velocity.copy(),
        )


def _frame_from_row(f: dict[str, Any], objects: list[ObjectRecord]) -> FrameRecord:
    gp = f["ground_plane"]
    syn = f["synthetic"]
    pose = f["camera_to_world"]
    return FrameRecord(
        frame_id=f["frame_id"], source=f["source"], view=f["view"], image=f["image"], width=f["width"],
        height=f["height"], K=np.asarray(f["K"], dtype=np.float64), objects=objects,
        ignore_regions=[IgnoreRegion(np.asarray(r["bbox"], dtype=np.float64), r["label"]) for r in f["ignore_regions"]],
        ground_plane=None if gp is None else Plane(gp["normal"], gp["offset"]),
        camera_height=f["camera_height"], camera_pitch=f["camera_pitch"], group=f["group"],
        synthetic=None if syn is None else SyntheticInfo(**syn), schema_version=f["schema_version"],
        sequence=f["sequence"], timestamp=f["timestamp"], pair=f["pair"],
        camera_to_world=None if pose is None else np.asarray(pose, dtype=np.float64),
    )


def read_manifest(root: Path) -> dict[str, Any]:
    """A dataset folder's manifest.json, {} when it has none; checked against its schema first
    (check_manifest), so that no consumer meets a list where it expects an object, a string where
    it expects a number, or a taxonomy that names a file. Any failure is a ManifestError naming the
    file and the field.

    The file is read as a regular file of at most MANIFEST_MAX_BYTES (omnigen.untrusted): a
    manifest replaced by a FIFO or a link to a device would otherwise block or fill memory.
    """
    path = Path(root) / MANIFEST
    if not path.exists():
        return {}
    try:
        manifest = json.loads(read_regular(path, MANIFEST_MAX_BYTES))
    except UntrustedFileError as exc:
        raise ManifestError(path, "<file>", exc.message) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ManifestError(path, "<json>", f"not valid JSON: {exc}") from None
    except RecursionError:
        raise ManifestError(path, "<json>", "JSON nested too deeply to read") from None
    except OSError as exc:
        raise ManifestError(path, "<file>", f"cannot read: {exc.strerror or exc}") from None
    check_manifest(manifest, path)
    return manifest


# ---------------------------------------------------------------------------------------------
# The manifest's schema
# ---------------------------------------------------------------------------------------------

class _Bad(Exception):
    """A schema check's failure: the field and the message (ManifestError adds the file)."""

    def __init__(self, field: str, message: str):
        super().__init__(field, message)
        self.field, self.message = field, message


Check = Callable[[Any, str], None]


def _text(value: Any, field: str) -> None:
    if not isinstance(value, str):
        raise _Bad(field, f"expected a string, got {_kind(value)}")


def _count(value: Any, field: str) -> None:
    if type(value) is not int or value < 0:
        raise _Bad(field, f"expected a whole number >= 0, got {_kind(value)}")


def _seed(value: Any, field: str) -> None:
    if type(value) is not int or not 0 <= value <= SEED_MAX:
        raise _Bad(field, f"expected a seed in [0, 2**63 - 1], got {_kind(value)}")


def _test_fraction(value: Any, field: str) -> None:
    if type(value) not in (int, float) or not 0 <= value < 1:  # NaN fails the comparison
        raise _Bad(field, f"expected a number in [0, 1), got {_kind(value)}")


def _absolute_path(value: Any, field: str) -> None:
    """A merge records its sources resolved: a relative path would depend on the working folder."""
    _text(value, field)
    if not os.path.isabs(value) or "\0" in value:
        raise _Bad(field, f"expected an absolute path, got {value!r}")


def _optional(check: Check) -> Check:
    def optional(value: Any, field: str) -> None:
        if value is not None:
            check(value, field)
    return optional


def _list(check: Check) -> Check:
    def items(value: Any, field: str) -> None:
        if not isinstance(value, list):
            raise _Bad(field, f"expected a list, got {_kind(value)}")
        for i, item in enumerate(value):
            check(item, f"{field}[{i}]")
    return items


def _table(check: Check) -> Check:
    """An object whose every value passes `check` (its keys are names: sources, classes...)."""
    def table(value: Any, field: str) -> None:
        if not isinstance(value, dict):
            raise _Bad(field, f"expected an object, got {_kind(value)}")
        for key, item in value.items():
            check(item, f"{field}.{key}")
    return table


def _object(fields: dict[str, Check]) -> Check:
    """An object whose known fields pass their checks; other fields are left alone (a newer
    omnigen may write more, and nothing here reads them)."""
    def obj(value: Any, field: str) -> None:
        if not isinstance(value, dict):
            raise _Bad(field, f"expected an object, got {_kind(value)}")
        for key, check in fields.items():
            if key in value:
                check(value[key], f"{field}.{key}" if field else key)
    return obj


def _kind(value: Any) -> str:
    text = repr(value)
    return f"{type(value).__name__} {text if len(text) <= 60 else text[:57] + '...'}"


def _any_object(value: Any, field: str) -> None:
    _object({})(value, field)


_COUNTS = _table(_count)
_SPLIT = _object({"frames": _count, "objects": _count, "frames_by_source_view": _COUNTS, "objects_by_class": _COUNTS})
MANIFEST_SCHEMA: Check = _object({
    "format": _text, "schema_version": _count, "omnigen_version": _text, "records_sha256": _text, "name": _text,
    "counts": _object({"frames": _count, "objects": _count, "frames_by_source": _COUNTS, "frames_by_view": _COUNTS,
                       "objects_by_class": _COUNTS}),
    "taxonomy": _any_object,  # its content: omnigen.taxonomy.recorded_taxonomy
    "merge": _object({
        "sources": _list(_object({"path": _absolute_path, "name": _text, "records_sha256": _optional(_text),
                                  "frames": _count, "objects": _count, "frames_by_source": _COUNTS})),
        "seed": _seed, "test_fraction": _test_fraction, "split_files": _list(_text),
        "unique_images": _count, "duplicate_frames": _count, "duplicate_frame_ids": _list(_text)}),
    "splits": _table(_SPLIT),
    "render": _object({"width": _count, "height": _count, "seed": _seed}),
    "conversion": _object({"converter": _text}),
    "conversion_stats": _any_object,  # counts for people to read; no code reads them
})
"""What the fields a consumer reads must hold: merge --update reads `merge`, export `taxonomy`,
render and validate `render`, the converters `conversion`, stats and exports `name`."""


def check_manifest(manifest: Any, path: str | os.PathLike) -> None:
    """A ManifestError naming the first field that breaks MANIFEST_SCHEMA, or the taxonomy entry
    that is not a preset's name or a well-formed mapping."""
    try:
        MANIFEST_SCHEMA(manifest, "")
    except _Bad as exc:
        raise ManifestError(path, exc.field or "<manifest>", exc.message) from None
    try:
        recorded_taxonomy(manifest, path)
    except TaxonomyError as exc:
        raise ManifestError(path, exc.field, exc.message) from None
