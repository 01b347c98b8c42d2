"""Which job an output folder belongs to: the guard before a job deletes anything in it.

`omnigen merge` and `omnigen convert` rewrite their whole output, so a rerun deletes what an
earlier run of theirs left there and the new one no longer holds (records of frames now skipped,
pixels no longer used). Pointed at any other folder, say an unfinished render mistyped as
`--out`, that would destroy data. So each such job first claims its folder with a marker file
naming the job, and refuses a folder that holds anything it cannot tell is its own.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from omnigen.dataset import DatasetError, read_manifest
from omnigen.files import atomic_write_text

JOB_MARKER = ".omnigen-job"


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
    marker = out / JOB_MARKER
    if marker.exists():
        owner = marker.read_text().strip()
        if owner != job:
            raise DatasetError(f"{out}: made by 'omnigen {owner}' ({JOB_MARKER}), not 'omnigen {job}'; "
                               "refusing to overwrite it (choose a new or empty folder)")
        return
    if out.is_dir() and any(out.iterdir()):
        if not made_by_job(out):
            raise DatasetError(f"{out}: holds files that 'omnigen {job}' did not make; refusing to overwrite "
                               "them (choose a new or empty folder)")
    if mark:
        atomic_write_text(marker, job + "\n")
