"""Writing a dataset folder: records one by one, then the index and the manifest that seals them.

Every job that makes a dataset (a render, a conversion, a merge) writes it through DatasetWriter,
so that the folder's rules hold for all of them: records are written atomically (omnigen.files),
so a killed job leaves whole records or none, and a resumed one skips what exists; the manifest
is written last and is the seal: a folder without one is unfinished, and its records_sha256 lets
`omnigen validate` see any record changed since.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections import Counter
from pathlib import Path
from typing import Any, Collection

import numpy as np

from omnigen import __version__
from omnigen.conventions import FINE_CLASSES, SCHEMA_VERSION
from omnigen.dataset import MANIFEST, RECORDS_DIR, Dataset, DatasetError, check_record_name, record_files, record_path
from omnigen.files import LinkMode, atomic_write_bytes, atomic_write_json, dumps_json, link_file
from omnigen.index import DatasetIndex, IndexRows, records_fingerprint, write_index
from omnigen.progress import progress
from omnigen.record import FrameRecord, RecordError
from omnigen.tables import FrameTable, ObjectTable

FORMAT_NAME = "UrbanOmniView"


def update_records_digest(digest: "hashlib._Hash", name: str, data: bytes) -> None:
    """Fold one record file into the dataset's records_sha256 (name and bytes, in frame-id order)."""
    digest.update(name.encode() + b"\0" + data)


class DatasetWriter:
    """Writes a dataset frame by frame; safe to resume and to share between processes.

    Each record is written atomically to records/<frame_id>.json. `has()` lets a resumed job skip
    finished frames. `finalize()` (run once, after all writers are done) builds the index and
    the manifest from whatever records/ holds. A job that assembles a dataset from finished
    records and columns it already holds (a merge) places records with `link_record` /
    `write_record_bytes`, then calls `index_columns` and `seal` instead.
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
        return self.seal(self._index(DatasetIndex.from_rows(rows), key), digest.hexdigest(), extra or {})

    # -- a dataset assembled from finished records (a merge) -----------------------------------
    def unseal(self) -> None:
        """Remove manifest.json before any record changes, so an interrupted job never looks finished."""
        (self.root / MANIFEST).unlink(missing_ok=True)

    def drop_records_except(self, frame_ids: Collection[str]) -> list[str]:
        """Delete every record whose frame id is not in `frame_ids`; their ids, in frame-id order.

        Only records: a job that places pixels shared between frames (a merge) knows which files
        are still used and removes the rest itself, after placing the new ones. Unseals first: a
        folder whose records are changing must not look finished.
        """
        self.unseal()
        keep = set(frame_ids)
        dropped = []
        for e in record_files(self.root):
            if e.name[:-5] not in keep:
                Path(e.path).unlink()
                dropped.append(e.name[:-5])
        return dropped

    def write_record_bytes(self, frame_id: str, data: bytes) -> None:
        """Write a record given as the bytes of its file, atomically (durable as the writer is).

        For records already validated elsewhere (a source dataset's record with its paths
        rewritten); `write` validates and serialises a FrameRecord instead. The one check kept here
        is the cheap one a reader relies on: the record's frame_id is its file's name.
        """
        path = record_path(self.root, frame_id)
        try:
            named = json.loads(data).get("frame_id")
        except (json.JSONDecodeError, AttributeError):
            raise RecordError(frame_id, "<json>", "not a JSON object", path) from None
        check_record_name(named, path.name, path)
        atomic_write_bytes(path, data, durable=self.durable)

    def link_record(self, frame_id: str, src: str | os.PathLike, mode: LinkMode = "hardlink") -> str:
        """Place another dataset's finished record file as this one's record of `frame_id`; the
        mode used (omnigen.files.link_file). Records are immutable: a later rewrite replaces the
        file, never edits it, so a linked record never changes under its source."""
        return link_file(src, record_path(self.root, frame_id), mode)

    def index_columns(self, table: FrameTable, objects: ObjectTable,
                      attributes: list[dict[str, Any]] | None) -> Dataset:
        """Write the index of records/ from columns already in hand; returns the dataset, unsealed.

        Why: a merge assembles its columns from the sources' indexes, which costs seconds where
        parsing 40,000 records again costs minutes. The columns must describe records/ as it is
        now, frame for frame (DatasetIndex.from_columns says how they are laid out); a table whose
        frame ids are not those of records/ is refused, since a reader would trust the index.
        """
        entries = record_files(self.root)
        names = [e.name[:-5] for e in entries]
        if table.frame_id != names:
            missing, extra = sorted(set(table.frame_id) - set(names)), sorted(set(names) - set(table.frame_id))
            raise DatasetError(f"{self.root}: the index's frames are not those of {RECORDS_DIR}/ (no record for "
                               f"{missing[:3]}, not indexed {extra[:3]}, or not in frame-id order)")
        return self._index(DatasetIndex.from_columns(table, objects, attributes), records_fingerprint(entries))

    def seal(self, ds: Dataset, records_sha256: str, extra: dict[str, Any]) -> Dataset:
        """Write manifest.json (make_manifest of `ds`, `records_sha256` and `extra`) last: it
        seals the dataset. `records_sha256` folds every record of records/ in frame-id order
        (update_records_digest)."""
        ds.manifest = make_manifest(ds, records_sha256, extra)
        atomic_write_json(self.root / MANIFEST, ds.manifest, indent=2)
        return ds

    def _index(self, index: DatasetIndex, key: str) -> Dataset:
        write_index(self.root, index, key)  # not a cache: a job's index that cannot be written is an error
        return Dataset.from_index(self.root, index, manifest={})


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
