"""Atomic writes and image linking: the two ways omnigen puts bytes on disk.

Every file a reader trusts is written to a temporary name in the same folder, flushed, and then
renamed over the final name, so an interrupted job never leaves a half-written file that a later
read accepts. Temporary names start with TMP_PREFIX and readers skip them.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Literal

import orjson

TMP_PREFIX = ".tmp-"

# The process's umask, read once at import (reading it means setting it): files written through a
# temporary name get the mode open() would have given them, not mkstemp's owner-only 0600.
_UMASK = os.umask(0o022)
os.umask(_UMASK)

LinkMode = Literal["hardlink", "symlink", "copy"]
LINK_MODES: tuple[str, ...] = ("hardlink", "symlink", "copy")


def make_temp(folder: str | os.PathLike, suffix: str = "") -> tuple[int, str]:
    """A new temporary file in `folder` (its descriptor and name), named so readers skip it and
    readable as a file open() would create is: on a shared cluster other users read the dataset."""
    fd, tmp = tempfile.mkstemp(prefix=TMP_PREFIX, suffix=suffix, dir=folder)
    os.fchmod(fd, 0o666 & ~_UMASK)
    return fd, tmp


def atomic_write_bytes(path: str | os.PathLike, data: bytes, durable: bool = True) -> None:
    """Write `data` to `path` so that readers see either the old file or the whole new one.

    The rename alone makes the write atomic for other processes and survives the writer being
    killed. `durable` adds an fsync, so that the bytes also survive a power cut; bulk writers that
    seal their output with a fsynced manifest (merge) skip it per file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = make_temp(path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            if durable:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def dumps_json(obj: Any) -> str:
    """The one JSON style omnigen writes records in: sorted keys, compact, a trailing newline.

    Sorted keys and orjson's shortest round-trip floats make reruns byte-identical; orjson encodes
    several times faster than the json module, which matters at tens of thousands of records.
    Records are validated before they are written, so no NaN reaches a checked field (orjson would
    write it as null); free-form source attributes are the source's own values.
    """
    return orjson.dumps(obj, option=orjson.OPT_SORT_KEYS).decode() + "\n"


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int | None = None) -> None:
    if indent is None:
        atomic_write_text(path, dumps_json(obj))
    else:
        atomic_write_text(path, json.dumps(obj, sort_keys=True, indent=indent, allow_nan=False) + "\n")


def link_file(src: str | os.PathLike, dst: str | os.PathLike, mode: LinkMode = "hardlink") -> str:
    """Place `src` at `dst` without duplicating bytes where the file system allows.

    hardlink falls back to symlink (across file systems) and then to copy; symlink falls back to
    copy. Returns the mode actually used. The final name appears atomically. Works on plain
    strings: merges call it tens of thousands of times.
    """
    src, dst = os.fspath(src), os.fspath(dst)
    if mode not in LINK_MODES:
        raise ValueError(f"link mode must be one of {LINK_MODES}, got {mode!r}")
    folder, name = os.path.split(dst)
    tmp = os.path.join(folder, f"{TMP_PREFIX}{name}.{os.getpid()}")
    last_error: OSError | None = None
    for how in LINK_MODES[LINK_MODES.index(mode):]:
        for attempt in (0, 1):
            try:
                _remove_if_present(tmp)
                if how == "hardlink":
                    os.link(src, tmp)
                elif how == "symlink":
                    os.symlink(os.path.abspath(src), tmp)
                else:
                    shutil.copyfile(src, tmp)
                os.replace(tmp, dst)
                if how == "hardlink":  # rename() does nothing when both names already link one file (a rerun)
                    _remove_if_present(tmp)
                return how
            except FileNotFoundError as exc:
                if attempt == 0 and not os.path.isdir(folder or "."):
                    os.makedirs(folder, exist_ok=True)  # first file of its folder
                    continue
                last_error = exc
                break
            except OSError as exc:  # cross-device link, no symlink support, ...
                last_error = exc
                break
        _remove_if_present(tmp)
        if isinstance(last_error, FileNotFoundError) and not os.path.exists(src):
            break
    raise OSError(f"cannot place {src} at {dst}: {last_error}")


def _remove_if_present(path: str) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


def file_digest(path: str | os.PathLike, chars: int = 16) -> str:
    """The first `chars` hex digits of a file's SHA-256, read in pieces: what says two files of one
    name hold the same bytes (a checkpoint rewritten in place)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:chars]
