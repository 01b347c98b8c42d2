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

from omnigen.dataset import MANIFEST, RECORDS_DIR, record_files, update_records_digest
from omnigen.progress import progress
from omnigen.record import FrameRecord, RecordError


@dataclass(frozen=True)
class Problem:
    file: str
    field: str
    message: str

    def __str__(self) -> str:
        return f"{self.file}: {self.field}: {self.message}"


def check_dataset(root: str | os.PathLike, show_progress: bool = True) -> tuple[int, list[Problem]]:
    """Return (frames checked, problems): schema, finite values, files present, unique ids."""
    root = Path(root)
    problems: list[Problem] = []
    if not (root / RECORDS_DIR).is_dir():
        return 0, [Problem(str(root), RECORDS_DIR, "missing: not an UrbanOmniView dataset")]
    if not (root / MANIFEST).exists():
        problems.append(Problem(str(root), MANIFEST, "missing (the dataset was never finalized)"))
    entries = record_files(root)
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
        files = [("image", rec.image)]
        if rec.synthetic is not None:
            files += [("synthetic.depth", rec.synthetic.depth), ("synthetic.instance", rec.synthetic.instance)]
        for field, rel in files:
            if not (root / rel).is_file():
                problems.append(Problem(e.path, field, f"file {rel} not found"))
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
