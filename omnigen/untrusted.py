"""Reading files whose names and contents come from outside: kept inside a root, regular, size-capped.

A source dataset names its own files (DAIR-V2X's data_info.json holds paths; any tree can hold
symbolic links). Followed blindly, such a name reads /dev/zero until memory runs out, blocks for
ever on a FIFO, or links a file from elsewhere on the machine into a dataset that is then shared.
Every read of a file that a source (or a copied dataset) names goes through here, so that the
three checks are made the same way everywhere: the path, links resolved, lies inside the folder
the user gave; it names a regular file; and the file is no larger than the caller's cap, checked
before a byte is read. docs/untrusted-inputs.md states the promise.

The failures are UntrustedFileError (file and message); a missing file stays FileNotFoundError,
so that callers keep their own "missing" messages.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO


class UntrustedFileError(ValueError):
    """A file that must not be read: outside its root, not a regular file, or too large."""

    def __init__(self, file: str | os.PathLike, message: str):
        self.file = os.fspath(file)
        self.message = message
        super().__init__(f"{self.file}: {message}")

    def __reduce__(self) -> tuple:
        return (type(self), (self.file, self.message))


def resolve_inside(root: str | os.PathLike, path: str | os.PathLike) -> Path:
    """`path` (relative to root, or absolute) with every link resolved; an error unless inside root.

    Resolving first is what makes the check hold: `a/../../x` and a link `a -> /etc` are caught
    by where they lead, not by how they are spelled. A path that does not exist resolves as far as
    it does and is judged the same way (the caller then reports it missing). The root is resolved
    on every call, not cached: a relative root means the working folder of now, and a root that is
    a link may have been re-pointed (a few lstat calls, against milliseconds to decode an image).
    """
    real_root = os.path.realpath(root)
    resolved = os.path.realpath(os.path.join(real_root, path))
    if resolved != real_root and not resolved.startswith(real_root.rstrip(os.sep) + os.sep):
        raise UntrustedFileError(path, f"leads outside {root} (to {resolved})")
    return Path(resolved)


def _check_regular(st: os.stat_result, path: str | os.PathLike, max_bytes: int) -> None:
    if not stat.S_ISREG(st.st_mode):
        raise UntrustedFileError(path, f"not a regular file ({_kind(st.st_mode)})")
    if st.st_size > max_bytes:
        raise UntrustedFileError(path, f"{st.st_size} bytes, more than the {max_bytes} allowed")


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a plain file"


def open_regular(path: str | os.PathLike, max_bytes: int) -> BinaryIO:
    """The file opened for reading, once it is known to be a regular file of at most max_bytes.

    os.stat decides before anything is opened (opening a FIFO would block until a writer came).
    The open itself is non-blocking and the descriptor is checked again, so a file swapped for a
    FIFO or a device between the two checks is still refused.
    """
    _check_regular(os.stat(path), path, max_bytes)
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        _check_regular(os.fstat(fd), path, max_bytes)
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_regular(path: str | os.PathLike, max_bytes: int) -> bytes:
    """All bytes of a regular file of at most max_bytes (see open_regular); never reads past the cap."""
    with open_regular(path, max_bytes) as fh:
        data = fh.read(max_bytes + 1)
    if len(data) > max_bytes:  # grew after the check
        raise UntrustedFileError(path, f"more than the {max_bytes} bytes allowed")
    return data


def check_regular(path: str | os.PathLike, max_bytes: int) -> None:
    """Only the checks of open_regular, for a file that is linked rather than read."""
    _check_regular(os.stat(path), path, max_bytes)
