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
import functools
import multiprocessing
import os
import signal
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Hashable, Iterator, Sequence

from omnigen.files import LINK_MODES, atomic_write_bytes, link_file
from omnigen.images import ImageError, check_image
from omnigen.index import IndexRows
from omnigen.options import integer
from omnigen.outputs import refuse_inputs
from omnigen.ownership import claim_output, manifest_of
from omnigen.progress import print_table, progress
from omnigen.record import FrameRecord, RecordError
from omnigen.untrusted import UntrustedFileError, read_regular, resolve_inside
from omnigen.writer import DatasetWriter


class SourceError(ValueError):
    """Bad input in a source dataset; names the file and the line or field."""

    def __init__(self, file: str | Path, where: str, message: str):
        self.file = str(file)
        self.where = where
        self.message = message
        super().__init__(f"{file}: {where}: {message}" if where else f"{file}: {message}")

    def __reduce__(self) -> tuple[Any, ...]:
        # Rebuilt from its three parts, so that it crosses a process boundary (workers > 1).
        return (type(self), (self.file, self.where, self.message))


TEXT_FILE_MAX_BYTES = 8 * 2**20
"""Largest label, calibration or other per-frame text file a converter reads. A KITTI label line is
under 100 bytes and a DAIR-V2X label object under 1 kB, so 8 MiB holds thousands of objects; the cap
exists so that a path to a huge file (or one that never ends) costs a skip, not the machine's memory."""


def source_path(root: str | Path, path: str | Path, frame: str, named_by: str = "") -> Path:
    """`path` (relative to root, or absolute) with links resolved, refused unless it lies inside root.

    A source names its own files; without this, `../../x`, `/etc/x` or a link out of the tree would
    be read, or (an image) hard-linked into the output. The error names the frame and who named
    the path (`named_by`, e.g. the data_info.json field).
    """
    try:
        return resolve_inside(root, path)
    except UntrustedFileError as exc:
        raise SourceError(Path(root) / path, "", f"frame {frame}: {exc.message}; only files inside the source folder are "
                          f"read{f' ({named_by})' if named_by else ''}") from None


def read_source_bytes(path: str | Path, max_bytes: int = TEXT_FILE_MAX_BYTES, named_by: str = "") -> bytes:
    """A source file's bytes: a regular file of at most max_bytes, else a SourceError naming it.

    A missing file stays FileNotFoundError, so that each converter says who expected it.
    """
    try:
        return read_regular(path, max_bytes)
    except UntrustedFileError as exc:
        raise SourceError(path, "", f"{exc.message}{f' ({named_by})' if named_by else ''}") from None
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise SourceError(path, "", f"cannot read: {exc.strerror or exc}") from None


def source_image_size(source: Path | bytes, file: str | Path) -> tuple[int, int]:
    """(width, height) of a whole image (omnigen.images.check_image: pixel cap, full decode).

    The header alone is not trusted: a truncated file keeps its header and would fail only in
    training, and a tiny file can claim a size that takes gigabytes to decode.
    """
    try:
        return check_image(source, file)
    except FileNotFoundError:
        raise SourceError(file, "", "missing image") from None
    except ImageError as exc:
        raise SourceError(exc.file, "", exc.message) from None


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
    stats: dict[str, int] = field(default_factory=dict)
    """Per-frame counts the converter wants summed into the report and the manifest
    (e.g. objects dropped for lying outside the image); empty for converters that keep none."""


@dataclass
class ConversionReport:
    written: int = 0
    objects: int = 0
    ignore_regions: int = 0
    skips: list[SourceError] = field(default_factory=list)
    link_modes: Counter = field(default_factory=Counter)
    seconds: float = 0.0
    stats: Counter = field(default_factory=Counter)  # sum of ConvertedFrame.stats over written frames
    stale: list[str] = field(default_factory=list)  # frames an earlier run into --out left, removed


MAX_WORKERS = 256
"""Most --workers: each is a forked copy of this process, and more than a machine's cores only
contend for them; 0 or a negative number ran one process without a word."""


def add_common_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, required=True, help="output dataset folder")
    p.add_argument("--link", choices=LINK_MODES, default="hardlink",
                   help="how images are placed: hardlink (falls back to symlink, then copy), symlink or copy")
    p.add_argument("--strict", action="store_true", help="stop at the first bad frame instead of skipping it")
    p.add_argument("--limit", type=integer(1), default=None, help="convert only the first N frames (default: all)")
    p.add_argument("--workers", type=integer(1, MAX_WORKERS), default=default_workers(),
                   help="processes converting frames (default: the CPUs available, at most 8); "
                        "the dataset is the same for any number")
    p.add_argument("--durable", action="store_true",
                   help="fsync every record as it is written (slow on busy disks); by default one flush "
                        "before the manifest seals the dataset")


def default_workers() -> int:
    return max(1, min(len(os.sched_getaffinity(0)), 8))


def select_keys(keys: list, limit: int | None, root: str | Path, what: str = "frames") -> list:
    """The keys a run converts (the first `limit` with --limit); no keys at all is an input error."""
    if limit is not None:
        keys = keys[: max(0, limit)]
    if not keys:
        raise SourceError(root, "", f"no {what} found")
    return keys


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
    workers: int = 1,
    durable: bool = True,
    inputs: Sequence[str | os.PathLike] = (),
) -> ConversionReport:
    """Convert every key, write the dataset, and return the report (skips included).

    `inputs` are the source tree (and image folder) read: `out` may not be one of them, lie inside
    one, or hold one (omnigen.outputs.refuse_inputs), since a rerun deletes what it no longer holds.

    With strict=True the first SourceError or RecordError propagates and nothing is finalized.

    With workers > 1 (and at least PARALLEL_MIN_FRAMES keys) whole frames (convert, place the
    image, validate and write the record) run in that many forked processes; results come back in
    key order, so skips, the report and the dataset equal those of workers=1. Workers write,
    rather than this process, because one record's validation and durable write cost as much as
    its conversion. `convert_one` must then be safe in a forked child (reopen shared file handles
    there). With --strict, frames after the first bad one that were already in flight may still be
    written; a rerun rewrites them identically.

    durable=False skips the fsync per record (on a busy disk it costs more than converting the
    frame) and instead flushes everything once (os.sync) before the manifest, which is written
    last and seals the dataset: a power cut can then cost an unfinished run, never a finished one.
    A killed process is safe either way (records appear by atomic rename).

    Stats the frames carry are summed into the report and, when any, into the manifest under
    "conversion_stats".
    """
    start = time.perf_counter()
    converter = (manifest_extra or {}).get("conversion", {}).get("converter", "")
    job = f"convert {converter}".strip()
    refuse_inputs(out, inputs, job)
    # an output from before the marker is recognised by its converter's name, never by a missing one
    claim_output(out, job, lambda folder: bool(converter)
                 and manifest_of(folder).get("conversion", {}).get("converter") == converter)
    writer = DatasetWriter(out, durable=durable)
    report = ConversionReport()
    outcomes = _outcomes(keys, convert_one, writer, Path(out), link, workers)
    for key, outcome in progress(outcomes, desc=desc, total=len(keys), unit="frame"):
        if isinstance(outcome, (SourceError, RecordError)):
            if strict:
                raise outcome
            exc = outcome
            report.skips.append(exc if isinstance(exc, SourceError) else SourceError(exc.file or str(key), exc.field, exc.message))
            continue
        writer.adopt(outcome.rows)
        report.link_modes[outcome.link_mode] += 1
        report.written += 1
        report.objects += len(outcome.rows.objects)
        report.ignore_regions += len(outcome.rows.frame.ignore_regions)
        report.stats.update(outcome.stats)
    extra = dict(manifest_extra or {})
    if report.stats:
        extra["conversion_stats"] = dict(sorted(report.stats.items()))
    report.stale = writer.drop_unwritten()  # the dataset holds this run's frames, no earlier run's
    if not durable:
        os.sync()  # one flush for every record, before the manifest seals them
    writer.finalize(extra)
    report.seconds = time.perf_counter() - start
    return report


@dataclass
class _Written:
    """What a written frame reports back: its index rows, link mode and counts."""

    rows: IndexRows
    link_mode: str
    stats: dict[str, int]


Outcome = _Written | SourceError | RecordError

PARALLEL_MIN_FRAMES = 64
"""Below this many frames, forking workers costs more than it saves."""


def _convert_and_write(key: Hashable, convert_one: Callable[[Any], ConvertedFrame], writer: DatasetWriter,
                       out: Path, link: str) -> Outcome:
    """One frame, start to finish: the image is placed before the record, the frame's commit marker.

    Input errors are returned, not raised; anything else (KeyboardInterrupt, a bug) propagates.
    """
    image_dst = None
    frame = None
    try:
        frame = convert_one(key)
        image_dst = out / frame.record.image
        mode = frame.image.place(image_dst, link)
        rows = writer.write(frame.record)  # validates first; the record lands last, as the commit marker
    except (SourceError, RecordError) as exc:
        if image_dst is not None and frame is not None and not writer.has(frame.record.frame_id):
            image_dst.unlink(missing_ok=True)
        return exc
    return _Written(rows, mode, frame.stats)


def _outcomes(keys: Sequence[Hashable], convert_one: Callable[[Any], ConvertedFrame], writer: DatasetWriter,
              out: Path, link: str, workers: int) -> Iterator[tuple[Hashable, Outcome]]:
    """(key, outcome) in key order, from this process or from forked workers."""
    if workers <= 1 or len(keys) < PARALLEL_MIN_FRAMES:
        for key in keys:
            yield key, _convert_and_write(key, convert_one, writer, out, link)
        return
    writer.keep_written = False  # seen by the forked copies; this process keeps their rows via adopt()
    try:
        yield from _parallel_outcomes(keys, functools.partial(
            _convert_and_write, convert_one=convert_one, writer=writer, out=out, link=link), workers)
    finally:
        writer.keep_written = True


_worker_task: Callable[[Hashable], Outcome] | None = None
"""What a forked worker runs per key; set in the parent just before the fork."""


@dataclass
class _WorkerFailure:
    """An exception that is not an input error, carried out of a worker as text."""

    kind: str
    text: str


def _in_worker(key: Hashable) -> tuple[Hashable, Any]:
    assert _worker_task is not None
    try:
        outcome = _worker_task(key)
    except BaseException as exc:  # KeyboardInterrupt and bugs: report them, never lose the task
        return key, _WorkerFailure(type(exc).__name__, traceback.format_exc())
    if isinstance(outcome, RecordError):  # its pickled form would lose the fields: carry them
        return key, ("RecordError", outcome.frame_id, outcome.field, outcome.message, outcome.file)
    return key, outcome


def _parallel_outcomes(keys: Sequence[Hashable], task: Callable[[Hashable], Outcome],
                       workers: int) -> Iterator[tuple[Hashable, Outcome]]:
    global _worker_task
    chunk = max(1, min(32, len(keys) // (workers * 16)))
    _worker_task = task
    try:
        # Leaving the pool terminates the workers. They ignore Ctrl-C: this process gets it and stops them.
        with multiprocessing.get_context("fork").Pool(workers, initializer=signal.signal,
                                                      initargs=(signal.SIGINT, signal.SIG_IGN)) as pool:
            for key, result in pool.imap(_in_worker, keys, chunksize=chunk):
                if isinstance(result, _WorkerFailure):
                    if result.kind == "KeyboardInterrupt":
                        raise KeyboardInterrupt
                    raise RuntimeError(f"converting {key!r} failed in a worker:\n{result.text}")
                if isinstance(result, tuple):
                    result = RecordError(*result[1:])
                yield key, result
    finally:
        _worker_task = None


def print_report(title: str, report: ConversionReport) -> int:
    """Summary table, then every skip; returns the exit code (1 if any frame was skipped)."""
    links = ", ".join(f"{k} {v}" for k, v in sorted(report.link_modes.items())) or "-"
    rate = report.written / report.seconds if report.seconds > 0 else 0.0
    print_table(title, ["frames", "objects", "ignore regions", "skipped", "images", "seconds", "frames/s"],
                [[report.written, report.objects, report.ignore_regions, len(report.skips), links,
                  round(report.seconds, 2), round(rate, 1)]])
    if report.stale:
        print(f"  removed {len(report.stale)} frames an earlier run left in the output and this one did not "
              f"write: {', '.join(report.stale[:5])}{' ...' if len(report.stale) > 5 else ''}")
    for s in report.skips:
        print(f"  skipped: {s}")
    return 1 if report.skips else 0
