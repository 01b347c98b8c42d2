"""`omnigen validate`: every check a dataset must pass before anyone trains on it.

Unlike Dataset.open, which stops at the first bad record, this reads every record and collects
every problem, so a user fixes a converter once rather than once per error.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

from omnigen.cooperation import Sighting, disagreements, jumps, sightings
from omnigen.dataset import (MANIFEST, MANIFEST_MAX_BYTES, RECORDS_DIR, RENDER_ARGS_FILE, ManifestError, parse_record,
                             read_manifest, read_record_bytes, record_files)
from omnigen.images import ImageError, check_image
from omnigen.plausible import record_problems
from omnigen.progress import progress
from omnigen.record import FrameRecord, RecordError
from omnigen.untrusted import UntrustedFileError, read_regular
from omnigen.writer import update_records_digest


@dataclass(frozen=True)
class Problem:
    file: str
    field: str
    message: str

    def __str__(self) -> str:
        return f"{self.file}: {self.field}: {self.message}"


def check_dataset(root: str | os.PathLike, show_progress: bool = True) -> tuple[int, list[Problem]]:
    """Return (frames checked, problems): the manifest's schema, schema and finite values of each
    record, plausible values (omnigen.plausible: whoever wrote the record), files present, unique
    ids, images whole (decoded in full, omnigen.images.check_image) and of the record's size; across
    the frames of a sequence, views that disagree on a track and tracks that jump
    (omnigen.cooperation)."""
    root = Path(root)
    if not (root / RECORDS_DIR).is_dir():
        return 0, [Problem(str(root), RECORDS_DIR, "missing: not an UrbanOmniView dataset")]
    problems: list[Problem] = []
    manifest = _manifest(root, problems)
    entries = record_files(root)
    render, render_source = _render_settings(root, manifest, problems)
    digest = hashlib.sha256()
    seen: list[Sighting] = []
    files: dict[str, str] = {}
    for e in progress(entries, desc="validating", unit="frame", disable=not show_progress):
        try:
            data = read_record_bytes(e.path)
            update_records_digest(digest, e.name, data)
            rec = parse_record(data, e.path)
        except RecordError as exc:
            problems.append(Problem(e.path, exc.field, exc.message))
            continue
        problems += _record_problems(root, e, rec, render, render_source)
        seen += sightings(rec)
        files[rec.frame_id] = e.path
    problems += _sequence_problems(seen, files)
    if manifest is not None and manifest.get("records_sha256") != digest.hexdigest():
        problems.append(Problem(str(root / MANIFEST), "records_sha256",
                                "does not match records/ (an interrupted or unfinished write?)"))
    return len(entries), problems


def _sequence_problems(seen: list[Sighting], files: dict[str, str]) -> list[Problem]:
    """One line per track that two views place apart at one instant, or that jumps between two
    instants: named by the first frame's file, the message naming both frames and the track."""
    found = [*disagreements(seen), *jumps(seen)]
    return [Problem(files[f.frame_a], "objects.track_id", str(f)) for f in found]


def _manifest(root: Path, problems: list[Problem]) -> dict | None:
    """The manifest checked against its schema (omnigen.dataset.read_manifest); None, with the
    problem noted, when it is missing or broken."""
    if not (root / MANIFEST).exists():
        problems.append(Problem(str(root), MANIFEST, "missing (the dataset was never finalized)"))
        return None
    try:
        return read_manifest(root)
    except ManifestError as exc:
        problems.append(Problem(exc.file, exc.field, exc.message))
        return None


def _record_problems(root: Path, e: os.DirEntry, rec: FrameRecord, render: dict, render_source: str) -> list[Problem]:
    """Everything wrong with one parsed record: its name, its values, its files."""
    problems = [Problem(e.path, field, message) for field, message in record_problems(rec)]
    if e.name != f"{rec.frame_id}.json":
        problems.append(Problem(e.path, "frame_id", f"{rec.frame_id!r} does not match the file name"))
    if not rec.frame_id.startswith(f"{rec.source}-"):
        problems.append(Problem(e.path, "frame_id", f"{rec.frame_id!r} is not prefixed by its source '{rec.source}-'"))
    if render and rec.synthetic is not None:
        problems += _render_problems(e.path, rec, render, render_source)
    files = [("image", rec.image)]
    if rec.synthetic is not None:
        files += [("synthetic.depth", rec.synthetic.depth), ("synthetic.instance", rec.synthetic.instance)]
    for field, rel in files:
        if not (root / rel).is_file():
            problems.append(Problem(e.path, field, f"file {rel} not found"))
        elif field == "image":
            problems.extend(_image_problems(root / rel, rec, e.path))
    return problems


def _image_problems(path: Path, rec: FrameRecord, record_file: str) -> list[Problem]:
    """A frame's image decoded in full (a truncated file keeps its header) and its size against the record."""
    try:
        width, height = check_image(path)
    except ImageError as exc:
        return [Problem(record_file, "image", f"{rec.image}: {exc.message}")]
    if (width, height) != (rec.width, rec.height):
        return [Problem(record_file, "image", f"{rec.image} is {width}x{height}, the record says {rec.width}x{rec.height}")]
    return []


def _render_settings(root: Path, manifest: dict | None, problems: list[Problem]) -> tuple[dict, str]:
    """A render folder's arguments (its .render-args.json, else its manifest's `render` entry)
    and where they were read; ({}, "") for any other dataset. The arguments file is read as a
    regular file of at most MANIFEST_MAX_BYTES (one replaced by a FIFO would block validate)."""
    path = root / RENDER_ARGS_FILE
    if path.exists():
        try:
            data = json.loads(read_regular(path, MANIFEST_MAX_BYTES))
        except UntrustedFileError as exc:
            problems.append(Problem(str(path), "<file>", exc.message))
            return {}, ""
        except (ValueError, OSError) as exc:
            problems.append(Problem(str(path), "<json>", f"not readable as JSON: {exc}"))
            return {}, ""
        if isinstance(data, dict) and data:
            return data, str(path)
    render = (manifest or {}).get("render")
    return (render, str(root / MANIFEST)) if render else ({}, "")


def _render_problems(file: str, rec: FrameRecord, render: dict, source: str) -> list[Problem]:
    """A rendered frame that disagrees with its folder's arguments: frames of two settings mixed
    (a resumed render with another --width, say), which the manifest would misdescribe."""
    syn = rec.synthetic
    got = {"width": rec.width, "height": rec.height, "synthetic.rig": syn.rig, "synthetic.scene": syn.scene,
           "synthetic.seed": syn.seed, "synthetic.weather.kind": syn.weather.get("kind"),
           "synthetic.lighting.time_of_day": syn.lighting.get("time_of_day")}
    want = {"width": render.get("width"), "height": render.get("height"), "synthetic.rig": render.get("rig"),
            "synthetic.scene": render.get("scene"), "synthetic.seed": render.get("seed"),
            "synthetic.weather.kind": render.get("weather"), "synthetic.lighting.time_of_day": render.get("time_of_day")}
    return [Problem(file, k, f"{got[k]!r} but the folder was rendered with {want[k]!r} ({source})")
            for k in got if want[k] is not None and got[k] != want[k]]
