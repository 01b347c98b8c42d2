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

from omnigen.dataset import MANIFEST, RECORDS_DIR, RENDER_ARGS_FILE, record_files
from omnigen.images import ImageError, check_image
from omnigen.progress import progress
from omnigen.record import FrameRecord, RecordError
from omnigen.writer import update_records_digest


@dataclass(frozen=True)
class Problem:
    file: str
    field: str
    message: str

    def __str__(self) -> str:
        return f"{self.file}: {self.field}: {self.message}"


def check_dataset(root: str | os.PathLike, show_progress: bool = True) -> tuple[int, list[Problem]]:
    """Return (frames checked, problems): schema, finite values, files present, unique ids,
    images whole (decoded in full, omnigen.images.check_image) and of the record's size."""
    root = Path(root)
    problems: list[Problem] = []
    if not (root / RECORDS_DIR).is_dir():
        return 0, [Problem(str(root), RECORDS_DIR, "missing: not an UrbanOmniView dataset")]
    if not (root / MANIFEST).exists():
        problems.append(Problem(str(root), MANIFEST, "missing (the dataset was never finalized)"))
    entries = record_files(root)
    render, render_source = _render_settings(root)
    digest = hashlib.sha256()
    for e in progress(entries, desc="validating", unit="frame", disable=not show_progress):
        data = Path(e.path).read_bytes()
        update_records_digest(digest, e.name, data)
        try:
            rec = FrameRecord.from_dict(json.loads(data), file=e.path)
        except json.JSONDecodeError as exc:
            problems.append(Problem(e.path, "<json>", f"not valid JSON: {exc}"))
            continue
        except RecordError as exc:
            problems.append(Problem(e.path, exc.field, exc.message))
            continue
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
    manifest_path = root / MANIFEST
    if manifest_path.exists():
        try:
            recorded = json.loads(manifest_path.read_text()).get("records_sha256")
        except json.JSONDecodeError as exc:
            problems.append(Problem(str(manifest_path), "<json>", f"not valid JSON: {exc}"))
        else:
            if recorded != digest.hexdigest():
                problems.append(Problem(str(manifest_path), "records_sha256",
                                        "does not match records/ (an interrupted or unfinished write?)"))
    return len(entries), problems


def _image_problems(path: Path, rec: FrameRecord, record_file: str) -> list[Problem]:
    """A frame's image decoded in full (a truncated file keeps its header) and its size against the record."""
    try:
        width, height = check_image(path)
    except ImageError as exc:
        return [Problem(record_file, "image", f"{rec.image}: {exc.message}")]
    if (width, height) != (rec.width, rec.height):
        return [Problem(record_file, "image", f"{rec.image} is {width}x{height}, the record says {rec.width}x{rec.height}")]
    return []


def _render_settings(root: Path) -> tuple[dict, str]:
    """A render folder's arguments (its .render-args.json, else its manifest's `render` entry)
    and where they were read; ({}, "") for any other dataset."""
    for path, key in ((root / RENDER_ARGS_FILE, None), (root / MANIFEST, "render")):
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            continue  # absent, or broken (the manifest's own check says so)
        settings = data.get(key) if key else data
        if isinstance(settings, dict) and settings:
            return settings, str(path)
    return {}, ""


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
