"""`omnigen merge`: source datasets into one UrbanOmniView dataset with a held-out test split.

What a merge guarantees:
- every frame keeps its record and its (source-prefixed) frame id; a frame id found in two inputs
  is one frame when the records and the pixels (image, depth, instance) are identical, reported as
  a duplicate (the count and the first ids on the console and in the manifest), and an error
  naming the ids and the differing files otherwise: keeping either copy would silently drop the
  other's pixels, and which one is right is the user's call, not the merge's;
- images are deduplicated by content (SHA-256): frames whose pixels are identical share one file,
  and are put in one split group so the same image can never be both trained and tested on;
- the frames of one sequence (all its views) and the two frames of a cooperative pair are one
  split group too, whatever groups their source drew;
- the test split is deterministic for a seed, stratified by source and view, and keeps groups whole
  (omnigen.splits); split files given by the user, and an earlier merge's assignments under
  --update, are honoured;
- the output is byte-identical for identical inputs; records are written atomically and the
  manifest, written last, seals them (its records_sha256 is checked by `omnigen validate`), so an
  interrupted merge never looks finished.

The index of the merged dataset is assembled from the sources' indexes (columns), not by parsing
records again, which is what makes a 40,000-frame merge take seconds.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from omnigen.conventions import FINE_CLASSES
from omnigen.dataset import MANIFEST, Dataset, DatasetError, read_manifest, read_record_bytes, record_path
from omnigen.files import dumps_json, link_file
from omnigen.images import MAX_IMAGE_BYTES
from omnigen.outputs import refuse_inputs
from omnigen.ownership import claim_output, manifest_of, output_lock
from omnigen.progress import progress
from omnigen.splits import (SPLITS_DIR, SourceShare, assign_test_split, read_assignments, read_id_list, split_shares,
                            write_split)
from omnigen.tables import FrameTable, ObjectTable
from omnigen.taxonomy import Taxonomy, preset_taxonomy, recorded_taxonomy
from omnigen.untrusted import open_regular
from omnigen.writer import DatasetWriter, update_records_digest


@dataclass
class MergeReport:
    frames: int = 0
    objects: int = 0
    unique_images: int = 0
    duplicate_frames: int = 0
    duplicate_ids: list[str] = field(default_factory=list)  # frame-id order; same records and pixels, kept once
    by_source: Counter = field(default_factory=Counter)
    by_split: Counter = field(default_factory=Counter)
    test_fraction: float = 0.0  # the share asked for; by_split says what the whole groups gave
    link_modes: Counter = field(default_factory=Counter)
    seconds: float = 0.0
    unmatched_lines: Counter = field(default_factory=Counter)  # split file -> lines naming no frame
    shares: list[SourceShare] = field(default_factory=list)  # per source: test frames, frames, groups


@dataclass(frozen=True)
class _Frame:
    frame_id: str
    source_index: int  # which input
    row: int  # frame index in that input


class _Groups:
    """Union-find over frame ids: split groups joined by shared images."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}

    def find(self, x: str) -> str:
        self.parent.setdefault(x, x)
        while self.parent[x] != x:
            self.parent[x] = self.parent[self.parent[x]]
            x = self.parent[x]
        return x

    def union(self, a: str, b: str) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            lo, hi = sorted((ra, rb))
            self.parent[hi] = lo  # the smaller key represents: deterministic


DUPLICATES_SHOWN = 10
"""How many duplicate frame ids (or conflicting ones) a merge names, in the manifest and on the
console, beside their count: enough to find the overlapping sources, short enough to read."""


def _file_sha256(path: str | os.PathLike) -> str:
    """A source's pixel file's digest, read as a regular file (a FIFO would block the merge)."""
    with open_regular(path, MAX_IMAGE_BYTES) as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def _file_difference(a: str, b: str) -> str | None:
    """None when files a and b hold the same bytes, else how they differ. Cheapest test first: one
    file (same device and inode, as a hard-linked merge of merges has) is the same; sizes that differ
    differ; only files of one size are hashed."""
    try:
        sa, sb = os.stat(a), os.stat(b)
    except FileNotFoundError as exc:
        return f"{exc.filename} is missing"
    if (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino):
        return None
    if sa.st_size != sb.st_size:
        return f"{sa.st_size} and {sb.st_size} bytes"
    return None if _file_sha256(a) == _file_sha256(b) else "same size, different content"


def _pixel_differences(first: Dataset, other: Dataset, first_row: int, other_row: int) -> list[str]:
    """What differs between two sources' pixel files of one frame whose records are identical (so
    both name the same relative paths): one 'FIELD PATH differs (how)' per differing file."""
    rel = {"image": first.table.image[first_row]}
    syn = first.table.extras[first_row]["synthetic"]
    if syn is not None:
        rel.update(depth=syn["depth"], instance=syn["instance"])
    differences = []
    for key, path in rel.items():
        how = _file_difference(os.path.join(first.root, path), os.path.join(other.root, path))
        if how is not None:
            differences.append(f"{key} {path} differs ({how})")
    return differences


def _one_frame_per_id(datasets: list[Dataset], report: MergeReport) -> dict[str, _Frame]:
    """Every frame id once, from the first source that has it. A frame id in a later source too is
    a duplicate (reported) when its record and pixels are the same, and refused otherwise: all
    conflicts are gathered first, so the error names every id of the overlap at once."""
    frames: dict[str, _Frame] = {}
    conflicts: list[str] = []
    for k, ds in enumerate(datasets):
        for i, frame_id in enumerate(ds.table.frame_id):
            other = frames.get(frame_id)
            if other is None:
                frames[frame_id] = _Frame(frame_id, k, i)
                continue
            first = datasets[other.source_index]
            if read_record_bytes(record_path(first.root, frame_id)) != read_record_bytes(record_path(ds.root, frame_id)):
                raise DatasetError(f"frame {frame_id} is in {first.root} and {ds.root} "
                                   f"with different records; frame ids must be unique across sources")
            differences = _pixel_differences(first, ds, other.row, i)
            if differences:
                conflicts.append(f"{frame_id} in {first.root} and {ds.root}: {', '.join(differences)}")
            report.duplicate_ids.append(frame_id)
    if conflicts:
        raise DatasetError(f"frame ids in two sources with identical records but different pixels ({len(conflicts)}); "
                           f"refusing to keep one source's pixels and drop the other's: {'; '.join(conflicts[:DUPLICATES_SHOWN])}"
                           f"{'; ...' if len(conflicts) > DUPLICATES_SHOWN else ''} (remove the stale copy, or give "
                           "the frames distinct ids)")
    report.duplicate_ids.sort()
    report.duplicate_frames = len(report.duplicate_ids)
    return frames


def _made_by_merge(folder: Path) -> bool:
    """A merged dataset from before the .omnigen-job marker: its manifest has a merge section."""
    return "merge" in manifest_of(folder)


def _prepare_out(out: Path, update: bool) -> dict[str, Any]:
    """Check and claim the output folder; returns the earlier merge's manifest under --update."""
    manifest_path = out / MANIFEST
    if update and not manifest_path.exists():
        raise DatasetError(f"{out}: --update needs a finished merged dataset there (no {MANIFEST})")
    claim_output(out, "merge", _made_by_merge, mark=False)  # refused early; marked before the first deletion
    return read_manifest(out) if update else {}


def merge(
    sources: list[Path],
    out: Path,
    taxonomy: Taxonomy | None = None,
    test_fraction: float | None = None,
    seed: int | None = None,
    split_files: list[Path] | None = None,
    update: bool = False,
    link: str = "hardlink",
) -> MergeReport:
    """Merge `sources` into `out`. Unset options default to fine, 0.10 and 0; under `update`, to the
    earlier merge's, so that adding a source does not change the classes or the draw of the rest.

    The whole merge holds the lock on `out`: a second merge into it at the same time fails at once.
    """
    out = Path(out)
    refuse_inputs(out, [*sources, *(split_files or [])], "merge")  # a rerun deletes what it no longer holds
    claim_output(out, "merge", _made_by_merge, mark=False)  # a folder not ours is refused before the lock makes it
    with output_lock(out, "merge"):
        return _merge(sources, out, taxonomy, test_fraction, seed, split_files, update, link)


def _join_groups(groups: _Groups, frame_id: str, table, row: int) -> None:
    """Put the frame in its source's split group, and in one group with every frame of its
    sequence (all its views) and of its cooperative pair, whatever the source called a group: one
    world seen at one moment, or over time, in train and test would leak the test labels.
    Sequences and pairs are keyed without the source, so that a DAIR-V2X-C pair whose sides came
    through different sources stays joined ("seq:"/"pair:" cannot be a frame id, which has no ':')."""
    g = table.group[row]
    groups.union(frame_id, f"{table.source[row]}:{g}" if g else frame_id)
    for kind, key in (("seq", table.sequence[row]), ("pair", table.pair[row])):
        if key is not None:
            groups.union(frame_id, f"{kind}:{key}")


def _merge(sources: list[Path], out: Path, taxonomy: Taxonomy | None, test_fraction: float | None,
           seed: int | None, split_files: list[Path] | None, update: bool, link: str) -> MergeReport:
    start = time.perf_counter()
    previous = _prepare_out(out, update)
    earlier_merge = previous.get("merge", {})
    taxonomy = taxonomy or (recorded_taxonomy(previous) if update else preset_taxonomy("fine"))
    test_fraction = earlier_merge.get("test_fraction", 0.10) if test_fraction is None else test_fraction
    seed = earlier_merge.get("seed", 0) if seed is None else seed
    earlier = [s["path"] for s in earlier_merge.get("sources", [])]
    fixed: dict[str, str] = read_assignments(out) if update else {}
    paths = list(dict.fromkeys([*earlier, *(str(Path(s).resolve()) for s in sources)]))
    if not paths:
        raise ValueError("merge needs at least one source dataset")
    if str(out.resolve()) in paths:
        raise ValueError(f"{out}: the output cannot also be a source")
    datasets = [Dataset.open(p) for p in paths]

    # 1. Every frame once, in frame-id order.
    report = MergeReport()
    frames = _one_frame_per_id(datasets, report)
    order = sorted(frames)

    # 2. Pixels. Records keep their paths where they can (then the record file is linked as it is);
    # frames with identical images share the first one's file and a split group; a path already
    # taken by other pixels is renamed after the frame.
    groups = _Groups()
    owner_of_hash: dict[str, str] = {}
    placement = _Placement()
    rewrites: dict[str, dict[str, str]] = {}  # frame id -> {field: new path}
    for frame_id in progress(order, desc="hashing images", unit="frame"):
        f = frames[frame_id]
        ds = datasets[f.source_index]
        rel = ds.table.image[f.row]
        src = os.path.join(ds.root, rel)
        owner = owner_of_hash.setdefault(_file_sha256(src), frame_id)
        if owner != frame_id:  # same pixels as an earlier frame: use its file
            new = placement.final[("image", owner)]
            placement.final[("image", frame_id)] = new
        else:
            new = placement.claim("image", frame_id, rel, src)
        if new != rel:
            rewrites.setdefault(frame_id, {})["image"] = new
        syn = ds.table.extras[f.row]["synthetic"]
        if syn is not None:
            for key in ("depth", "instance"):
                new = placement.claim(key, frame_id, syn[key], os.path.join(ds.root, syn[key]))
                if new != syn[key]:
                    rewrites.setdefault(frame_id, {})[key] = new
        _join_groups(groups, frame_id, ds.table, f.row)
        groups.union(frame_id, owner)
    report.unique_images = len(owner_of_hash)

    # 3. Splits: user files first, then the seeded stratified draw over whole groups.
    by_suffix = _ids_by_source_suffix(order, datasets, frames) if split_files else {}
    for path in split_files or []:
        name = Path(path).stem
        for line in read_id_list(path):
            named = [line] if line in frames else by_suffix.get(line, [])
            if len({frames[f].source_index for f in named}) > 1:
                raise ValueError(f"{path}: {line!r} names a frame of more than one source ({', '.join(named[:3])}); "
                                 "write full frame ids (e.g. kitti-000123)")
            if not named:
                report.unmatched_lines[str(path)] += 1  # e.g. a split file of the whole source, merged in part
            for frame_id in named:
                fixed[frame_id] = name
    strata = {fid: f"{datasets[f.source_index].table.source[f.row]}/{datasets[f.source_index].table.view[f.row]}"
              for fid, f in frames.items()}
    group_of = {fid: groups.find(fid) for fid in order}
    assignment = assign_test_split(group_of, strata, test_fraction, seed, {k: v for k, v in fixed.items() if k in frames})
    report.shares = split_shares(group_of, strata, assignment)

    # 4. Records (paths rewritten), images, depth and instance files.
    claim_output(out, "merge", _made_by_merge)
    writer = DatasetWriter(out, durable=False)
    writer.drop_records_except(order)  # unseals first: unsealed until the end
    for rel, src in progress(placement.sources.items(), desc="linking pixels", unit="file"):
        mode = link_file(src, os.path.join(out, rel), link)
        if rel.startswith("images/"):
            report.link_modes[mode] += 1
    records_digest = hashlib.sha256()
    for frame_id in progress(order, desc="merging records", unit="frame"):
        f = frames[frame_id]
        ds = datasets[f.source_index]
        src = record_path(ds.root, frame_id)
        data = read_record_bytes(src)
        if frame_id in rewrites:
            data = _rewrite_paths(data, rewrites[frame_id])
            writer.write_record_bytes(frame_id, data)
        else:
            writer.link_record(frame_id, src, link)
        update_records_digest(records_digest, f"{frame_id}.json", data)
        report.by_source[ds.table.source[f.row]] += 1

    _remove_unreferenced(out, set(placement.sources))

    # 5. Index from the sources' columns, reordered.
    ds_out = writer.index_columns(*_merged_columns(datasets, frames, order, rewrites))

    # 6. Split files, then the manifest, which seals the dataset.
    by_split: dict[str, list[str]] = defaultdict(list)
    for fid in order:
        by_split[assignment[fid]].append(fid)
    for old in (out / SPLITS_DIR).glob("*.txt") if (out / SPLITS_DIR).is_dir() else []:
        if old.stem not in by_split:
            old.unlink()
    for name, ids in sorted(by_split.items()):
        write_split(out, name, ids)
    report.by_split = Counter({k: len(v) for k, v in by_split.items()})
    report.test_fraction = test_fraction
    extra = {
        "name": out.name,
        "taxonomy": taxonomy.to_dict(),
        "merge": {
            "sources": [_source_entry(p, ds) for p, ds in zip(paths, datasets)],
            "seed": seed,
            "test_fraction": test_fraction,
            "split_files": [str(Path(p).resolve()) for p in split_files or []],
            "unique_images": report.unique_images,
            "duplicate_frames": report.duplicate_frames,
            "duplicate_frame_ids": report.duplicate_ids[:DUPLICATES_SHOWN],
        },
        "splits": _split_counts(ds_out, assignment),
    }
    writer.seal(ds_out, records_digest.hexdigest(), extra)
    report.frames, report.objects = len(ds_out), len(ds_out.objects)
    report.seconds = time.perf_counter() - start
    return report


class _Placement:
    """Which source file lands at which path of the merged dataset."""

    FOLDERS = {"image": "images", "depth": "depth", "instance": "instance"}

    def __init__(self) -> None:
        self.sources: dict[str, str] = {}  # path in the merged dataset -> source file
        self.final: dict[tuple[str, str], str] = {}  # (field, frame id) -> path in the merged dataset

    def claim(self, field: str, frame_id: str, rel: str, src: str) -> str:
        """Keep `rel` unless another file holds it; then name the file after the frame."""
        taken = self.sources.get(rel)
        if taken is not None and taken != src:
            rel = f"{self.FOLDERS[field]}/{frame_id}{os.path.splitext(rel)[1]}"
            if self.sources.get(rel, src) != src:
                raise DatasetError(f"frame {frame_id}: cannot find a free path for its {field}")
        self.sources[rel] = src
        self.final[(field, frame_id)] = rel
        return rel


def _rewrite_paths(data: bytes, new: dict[str, str]) -> bytes:
    d = json.loads(data)
    if "image" in new:
        d["image"] = new["image"]
    for key in ("depth", "instance"):
        if key in new:
            d["synthetic"][key] = new[key]
    return dumps_json(d).encode()


def _remove_unreferenced(out: Path, referenced: set[str]) -> None:
    """Drop pixels an earlier merge into this folder placed and this one no longer uses."""
    for folder in ("images", "depth", "instance"):
        if (out / folder).is_dir():
            for p in (out / folder).iterdir():
                if f"{folder}/{p.name}" not in referenced:
                    p.unlink()


def _ids_by_source_suffix(order: list[str], datasets: list[Dataset], frames: dict[str, _Frame]) -> dict[str, list[str]]:
    """Split-file lines may name frames without their source prefix (KITTI's '000123')."""
    out: dict[str, list[str]] = defaultdict(list)
    for fid in order:
        f = frames[fid]
        prefix = datasets[f.source_index].table.source[f.row] + "-"
        if fid.startswith(prefix):
            out[fid[len(prefix):]].append(fid)
        out[fid].append(fid)
    return out


def _merged_columns(datasets: list[Dataset], frames: dict[str, _Frame], order: list[str],
                    rewrites: dict[str, dict[str, str]]) -> tuple[FrameTable, ObjectTable, list[dict[str, Any]] | None]:
    frame_base = np.cumsum([0] + [len(ds) for ds in datasets])
    object_base = np.cumsum([0] + [len(ds.objects) for ds in datasets])
    all_frames = FrameTable.concat([ds.table for ds in datasets])
    all_objects = ObjectTable.concat([ds.objects for ds in datasets], list(frame_base[:-1]))
    rows = [int(frame_base[frames[fid].source_index] + frames[fid].row) for fid in order]
    table = all_frames.take(rows)
    for i, fid in enumerate(order):
        new = rewrites.get(fid)
        if new:
            table.image[i] = new.get("image", table.image[i])
            syn = table.extras[i]["synthetic"]
            for key in ("depth", "instance"):
                if key in new:
                    syn[key] = new[key]
    table.extras_blob = json.dumps(table.extras).encode()
    new_index = np.full(len(all_frames), -1, dtype=np.int64)
    new_index[rows] = np.arange(len(rows))
    obj_new_frame = new_index[all_objects.frame]
    keep = np.flatnonzero(obj_new_frame >= 0)
    keep = keep[np.argsort(obj_new_frame[keep], kind="stable")]
    objects = all_objects.take(keep)
    objects.frame = obj_new_frame[keep].astype(np.int32)
    attributes = None
    if any(ds.has_source_attributes for ds in datasets):
        flat = [a for ds, n in zip(datasets, object_base[1:] - object_base[:-1])
                for a in (ds.source_attributes if ds.has_source_attributes else [{}] * int(n))]
        attributes = [flat[j] for j in keep]
    return table, objects, attributes


def _source_entry(path: str, ds: Dataset) -> dict[str, Any]:
    return {
        "path": path,
        "name": ds.manifest.get("name", Path(path).name),
        "records_sha256": ds.manifest.get("records_sha256"),
        "frames": len(ds),
        "objects": len(ds.objects),
        "frames_by_source": dict(sorted(Counter(ds.table.source).items())),
    }


def _split_counts(ds: Dataset, assignment: dict[str, str]) -> dict[str, Any]:
    """Per split: frames by source and view, objects by class."""
    out: dict[str, Any] = {}
    frame_split = np.array([assignment[fid] for fid in ds.table.frame_id], dtype=object)
    for name in sorted(set(assignment.values())):
        mask = frame_split == name
        idx = np.flatnonzero(mask)
        obj_mask = mask[ds.objects.frame] if len(ds.objects) else np.zeros(0, bool)
        out[name] = {
            "frames": int(mask.sum()),
            "objects": int(obj_mask.sum()),
            "frames_by_source_view": dict(sorted(Counter(f"{ds.table.source[i]}/{ds.table.view[i]}" for i in idx).items())),
            "objects_by_class": dict(sorted(Counter(np.asarray(FINE_CLASSES)[ds.objects.category[obj_mask]].tolist()).items())),
        }
    return out
