"""Reading back a rendered dataset folder, for the render tests (sequences, cooperative views, frames)."""

from __future__ import annotations

import json
from pathlib import Path

from omnigen.record import FrameRecord

SUBS = ("records", "images", "depth", "instance")


def read_records(root: Path) -> list[FrameRecord]:
    """Every record under root/records, in file-name order."""
    return [FrameRecord.from_dict(json.loads(p.read_text())) for p in sorted((root / "records").glob("*.json"))]


def same_files(a: Path, b: Path) -> None:
    """Every frame's files and the manifest (the index holds file times) byte for byte."""
    assert (a / "manifest.json").read_bytes() == (b / "manifest.json").read_bytes()
    for sub in SUBS:
        names = sorted(p.name for p in (a / sub).iterdir())
        assert names == sorted(p.name for p in (b / sub).iterdir()), sub
        for name in names:
            assert (a / sub / name).read_bytes() == (b / sub / name).read_bytes(), (sub, name)
