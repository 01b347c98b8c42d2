"""What every converter shares: input errors, the frame loop, linking, the closing summary.

A converter supplies the list of frame keys and a function turning one key into a record and its
image; `run_conversion` does the rest the same way for every dataset: bad frames are skipped and
listed (or stop the run with --strict), images are linked rather than copied, each frame's image is
placed before its record (the record is the frame's commit marker), and the dataset is finalized
(index and manifest) at the end. Conversion is deterministic, so a rerun after an interruption
rewrites the same bytes and yields the same dataset.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Hashable, Iterable, Sequence

from omnigen.dataset import DatasetWriter
from omnigen.files import LINK_MODES, atomic_write_bytes, link_file
from omnigen.progress import print_table, progress
from omnigen.record import FrameRecord, RecordError


class SourceError(ValueError):
    """Bad input in a source dataset; names the file and the line or field."""

    def __init__(self, file: str | Path, where: str, message: str):
        self.file = str(file)
        self.where = where
        self.message = message
        super().__init__(f"{file}: {where}: {message}" if where else f"{file}: {message}")


@dataclass
class ImageSource:
    """Where a frame's image comes from: a file to link, or bytes (e.g. read from a zip)."""

    suffix: str  # ".png", ".jpg"
    path: Path | None = None
    data: bytes | None = None

    def place(self, dst: Path, link: str) -> str:
        if self.path is not None:
            return link_file(self.path, dst, link)  # type: ignore[arg-type]
        assert self.data is not None
        atomic_write_bytes(dst, self.data)
        return "copy"


@dataclass
class ConvertedFrame:
    record: FrameRecord
    image: ImageSource


@dataclass
class ConversionReport:
    written: int = 0
    objects: int = 0
    ignore_regions: int = 0
    skips: list[SourceError] = field(default_factory=list)
    link_modes: Counter = field(default_factory=Counter)
    seconds: float = 0.0


def add_common_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, required=True, help="output dataset folder")
    p.add_argument("--link", choices=LINK_MODES, default="hardlink",
                   help="how images are placed: hardlink (falls back to symlink, then copy), symlink or copy")
    p.add_argument("--strict", action="store_true", help="stop at the first bad frame instead of skipping it")
    p.add_argument("--limit", type=int, default=None, help="convert only the first N frames")


def image_relpath(frame_id: str, suffix: str) -> str:
    """Where a frame's image lives inside a dataset."""
    return f"images/{frame_id}{suffix}"


def run_conversion(
    keys: Sequence[Hashable],
    convert_one: Callable[[Any], ConvertedFrame],
    out: Path,
    link: str = "hardlink",
    strict: bool = False,
    desc: str = "converting",
    manifest_extra: dict[str, Any] | None = None,
) -> ConversionReport:
    """Convert every key, write the dataset, and return the report (skips included).

    With strict=True the first SourceError or RecordError propagates and nothing is finalized.
    """
    start = time.perf_counter()
    writer = DatasetWriter(out)
    report = ConversionReport()
    for key in progress(keys, desc=desc, unit="frame"):
        image_dst = None
        try:
            frame = convert_one(key)
            image_dst = out / frame.record.image
            mode = frame.image.place(image_dst, link)
            writer.write(frame.record)  # validates first; the record lands last, as the commit marker
        except (SourceError, RecordError) as exc:
            if image_dst is not None and not writer.has(frame.record.frame_id):
                image_dst.unlink(missing_ok=True)
            if strict:
                raise
            report.skips.append(exc if isinstance(exc, SourceError) else SourceError(exc.file or str(key), exc.field, exc.message))
            continue
        report.link_modes[mode] += 1
        report.written += 1
        report.objects += len(frame.record.objects)
        report.ignore_regions += len(frame.record.ignore_regions)
    writer.finalize(manifest_extra)
    report.seconds = time.perf_counter() - start
    return report


def print_report(title: str, report: ConversionReport) -> int:
    """Summary table, then every skip; returns the exit code (1 if any frame was skipped)."""
    links = ", ".join(f"{k} {v}" for k, v in sorted(report.link_modes.items())) or "-"
    rate = report.written / report.seconds if report.seconds > 0 else 0.0
    print_table(title, ["frames", "objects", "ignore regions", "skipped", "images", "seconds", "frames/s"],
                [[report.written, report.objects, report.ignore_regions, len(report.skips), links,
                  round(report.seconds, 2), round(rate, 1)]])
    for s in report.skips:
        print(f"  skipped: {s}")
    return 1 if report.skips else 0


def first(items: Iterable[Any], default: Any = None) -> Any:
    return next(iter(items), default)
