"""A dataset folder's index (.index.npz): the content of every record as columns, in one file.

Why an index: parsing 40,000 JSON files costs tens of seconds, while reading one .npz with the
same content costs a fraction of one. The index is a cache of records/, keyed by a fingerprint of
that folder (names, sizes, modification times): an index whose key no longer matches is stale.
This module reads and writes it; when to rebuild it is the reader's decision (omnigen.dataset),
and writing it for a job's output the writer's (omnigen.writer).
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from omnigen.files import atomic_write_bytes
from omnigen.record import FrameRecord
from omnigen.tables import FrameTable, ObjectTable

INDEX_FILE = ".index.npz"
INDEX_VERSION = 3
"""Bumped whenever the columns change (3: the schema-2 sequence and track columns), so that an
older cache is stale and rebuilt from records/ instead of read with columns missing."""


def records_fingerprint(entries: list[os.DirEntry]) -> str:
    """Cheap identity of records/: names, sizes and modification times of every record file."""
    h = hashlib.sha256()
    for e in entries:
        st = e.stat()
        h.update(f"{e.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


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


@dataclass
class DatasetIndex:
    """What the index holds: frames (sorted by id), their objects, and where each frame's start.

    Objects are grouped by frame in frame order; frame i's objects are rows offsets[i] to
    offsets[i + 1]. `attributes_blob` is every object's source attributes as JSON, None when no
    object has any (most datasets: the blob would be a list of empty dicts).
    """

    table: FrameTable
    offsets: np.ndarray  # (F + 1,) int64
    objects: ObjectTable
    attributes_blob: bytes | None

    @classmethod
    def from_rows(cls, rows: Iterable[IndexRows]) -> "DatasetIndex":
        """The index of frames given as IndexRows, in any order (sorted here by frame id)."""
        rows = sorted(rows, key=lambda r: r.frame_id)
        counts = [len(r.objects) for r in rows]
        attributes = [a for r in rows for a in r.attributes]
        objects = (ObjectTable.concat([r.objects for r in rows], list(range(len(rows)))) if rows
                   else ObjectTable.from_records([]))
        return cls(FrameTable.from_records([r.frame for r in rows]), np.cumsum([0] + counts).astype(np.int64),
                   objects, json.dumps(attributes).encode() if any(attributes) else None)

    @classmethod
    def from_records(cls, records: Iterable[FrameRecord]) -> "DatasetIndex":
        return cls.from_rows(IndexRows.of(r) for r in records)

    @classmethod
    def from_columns(cls, table: FrameTable, objects: ObjectTable,
                     attributes: list[dict[str, Any]] | None) -> "DatasetIndex":
        """The index of columns already in hand (a merge assembles them from its sources' indexes).

        `table` is sorted by frame id, `objects` grouped by frame in that order (its `frame`
        column indexes `table`), `attributes` one dict per object or None.
        """
        frame = np.asarray(objects.frame)
        if len(frame) and (np.any(np.diff(frame) < 0) or frame[0] < 0 or frame[-1] >= len(table)):
            raise ValueError("objects must be grouped by frame, in the order of the frame table")
        if attributes is not None and len(attributes) != len(objects):
            raise ValueError(f"{len(attributes)} source attributes for {len(objects)} objects")
        offsets = np.concatenate([[0], np.cumsum(np.bincount(frame, minlength=len(table)))]).astype(np.int64)
        return cls(table, offsets, objects, json.dumps(attributes).encode() if attributes and any(attributes) else None)


def read_index(root: str | os.PathLike, key: str) -> DatasetIndex | None:
    """The index of `root` if it describes records/ as fingerprinted by `key`; None when it is
    missing, stale, of another version or unreadable (a foreign or corrupt cache: rebuild it)."""
    path = Path(root) / INDEX_FILE
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            header = json.loads(z["header"].tobytes())
            if header.get("version") != INDEX_VERSION or header.get("key") != key:
                return None
            table = FrameTable.from_arrays(z)
            offsets = z["offsets"]
            objects = ObjectTable.from_arrays(z)
            attributes = z["attributes"].tobytes() if "attributes" in z.files else None
    except (OSError, ValueError, KeyError):
        return None
    return DatasetIndex(table, offsets, objects, attributes)


def write_index(root: str | os.PathLike, index: DatasetIndex, key: str, cache: bool = False) -> None:
    """Write `index` as root/.index.npz (atomically), keyed by `key`, the fingerprint of records/ it describes.

    `cache`: the index is only a reader's cache, so a folder that cannot be written (read-only
    file system, no permission) keeps it in memory, with one line on stderr; a job that writes the
    dataset (a merge, a finalize) passes False and fails instead.
    """
    root = Path(root)
    arrays = index.objects.to_arrays()
    arrays.update(index.table.to_arrays())
    arrays["header"] = np.frombuffer(json.dumps({"version": INDEX_VERSION, "key": key}).encode(), dtype=np.uint8)
    arrays["offsets"] = index.offsets
    if index.attributes_blob is not None:
        arrays["attributes"] = np.frombuffer(index.attributes_blob, dtype=np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    try:
        atomic_write_bytes(root / INDEX_FILE, buf.getvalue())
    except OSError as exc:
        if not cache or exc.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
            raise
        print(f"{root}: cannot write {INDEX_FILE} ({os.strerror(exc.errno)}); using an index built in memory "
              f"for this run ({len(index.table)} frames)", file=sys.stderr)
