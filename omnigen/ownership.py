"""Which job an output folder belongs to: the guard before a job deletes anything in it.

`omnigen merge` and `omnigen convert` rewrite their whole output, so a rerun deletes what an
earlier run of theirs left there and the new one no longer holds (records of frames now skipped,
pixels no longer used). Pointed at any other folder, say an unfinished render mistyped as
`--out`, that would destroy data. So each such job first claims its folder with a marker file
naming the job, and refuses a folder that holds anything it cannot tell is its own.

The marker says whose a folder is, not who is writing it now: two merges into one folder at once
each found it their own and together left no images. `output_lock` makes a job the only writer.
"""

from __future__ import annotations

import fcntl
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

from omnigen.dataset import DatasetError, read_manifest
from omnigen.files import atomic_write_text
from omnigen.untrusted import UntrustedFileError, read_regular

JOB_MARKER = ".omnigen-job"
MARKER_MAX_BYTES = 4096  # a job's name and a newline


def manifest_of(folder: Path) -> dict[str, Any]:
    """The folder's dataset manifest, or {} when it has none or a broken one (then it is no
    dataset this job can recognise as its own)."""
    try:
        return read_manifest(folder)
    except (DatasetError, OSError, UnicodeDecodeError):
        return {}


def claim_output(out: str | Path, job: str, made_by_job: Callable[[Path], bool], mark: bool = True) -> None:
    """Mark `out` as the output of `job` (e.g. "merge", "convert kitti"), or refuse it.

    Claimed: a new or empty folder; one this job claimed before (a rerun, or the resumption of
    a run that was cut off); an output from before the marker existed that `made_by_job`
    recognises (by its manifest, say). Refused, with nothing touched: any other folder with files.
    `mark=False` only checks: a job that may still fail on its inputs checks early and marks
    just before its first deletion, so a failed run leaves no claim on an empty folder.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{out}: is a file, not a folder; 'omnigen {job}' writes a folder here (choose another "
                           "--out)")
    marker = out / JOB_MARKER
    if marker.exists() or marker.is_symlink():
        try:  # a regular file of a few bytes: a FIFO put there would block every job for ever
            owner = read_regular(marker, MARKER_MAX_BYTES).decode("utf-8", "replace").strip()
        except (OSError, UntrustedFileError) as exc:
            raise DatasetError(f"{marker}: cannot be read as a job marker ({exc}); refusing the folder (choose a "
                               "new or empty folder)") from None
        if owner != job:
            raise DatasetError(f"{out}: made by 'omnigen {owner}' ({JOB_MARKER}), not 'omnigen {job}'; "
                               "refusing to overwrite it (choose a new or empty folder)")
        return
    if out.is_dir() and any(out.iterdir()):
        if not made_by_job(out):
            first = min(p.name for p in out.iterdir())  # which file is in the way is what the user needs
            raise DatasetError(f"{out}: holds {first} (and perhaps more), which 'omnigen {job}' did not make; "
                               "refusing to overwrite them (choose a new or empty folder)")
    if mark:
        atomic_write_text(marker, job + "\n")


@contextmanager
def output_lock(out: str | Path, job: str) -> Iterator[None]:
    """Hold an exclusive lock on the folder `out` (created if missing) while the block runs.

    The lock is flock(2) on the folder itself, so no lock file is left in it or beside it, and the
    kernel drops it when the process dies (a killed job never leaves a stale lock). A second job
    that finds the folder locked fails at once rather than wait: two runs into one output are a
    mistake to report, not a queue. A folder this call created is removed again when the block
    fails and leaves it empty.
    """
    out = Path(out)
    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise DatasetError(f"{out}: another job is writing this folder now (it is locked); wait for it to "
                               f"end or choose another --out for 'omnigen {job}'") from None
        try:
            yield
        except BaseException:
            if made:
                try:
                    out.rmdir()  # only when empty
                except OSError:
                    pass
            raise
    finally:
        os.close(fd)  # releases the lock
