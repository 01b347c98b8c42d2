"""Atomic writes and image linking: the two ways omnigen puts bytes on disk.

Every file a reader trusts is written to a temporary name in the same folder, flushed, and then
renamed over the final name, so an interrupted job never leaves a half-written file that a later
read accepts. Temporary names start with TMP_PREFIX and readers skip them.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Literal

TMP_PREFIX = ".tmp-"

LinkMode = Literal["hardlink", "symlink", "copy"]
LINK_MODES: tuple[str, ...] = ("hardlink", "symlink", "copy")


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write `data` to `path` so that readers see either the old file or the whole new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=TMP_PREFIX, dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
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
    """The one JSON style omnigen writes: sorted keys, compact, a trailing newline.

    Sorted keys and a fixed float repr make reruns byte-identical.
    """
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False) + "\n"


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int | None = None) -> None:
    if indent is None:
        atomic_write_text(path, dumps_json(obj))
    else:
        atomic_write_text(path, json.dumps(obj, sort_keys=True, indent=indent, allow_nan=False) + "\n")


def link_file(src: str | os.PathLike, dst: str | os.PathLike, mode: LinkMode = "hardlink") -> str:
    """Place `src` at `dst` without duplicating bytes where the file system allows.

    hardlink falls back to symlink (across file systems) and then to copy; symlink falls back to
    copy. Returns the mode actually used. The final name appears atomically.
    """
    src, dst = Path(src), Path(dst)
    if mode not in LINK_MODES:
        raise ValueError(f"link mode must be one of {LINK_MODES}, got {mode!r}")
    dst.parent.mkdir(parents=True, exist_ok=True)
    order = LINK_MODES[LINK_MODES.index(mode):]
    last_error: OSError | None = None
    for how in order:
        tmp = dst.parent / f"{TMP_PREFIX}{dst.name}.{os.getpid()}"
        try:
            if tmp.exists() or tmp.is_symlink():
                tmp.unlink()
            if how == "hardlink":
                os.link(src, tmp)
            elif how == "symlink":
                os.symlink(os.path.abspath(src), tmp)
            else:
                shutil.copyfile(src, tmp)
            os.replace(tmp, dst)
            return how
        except OSError as exc:  # cross-device link, no symlink support, ...
            last_error = exc
            if tmp.exists() or tmp.is_symlink():
                tmp.unlink()
    raise OSError(f"cannot place {src} at {dst}: {last_error}")
