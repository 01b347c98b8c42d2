"""Where a command may write: nothing the user owns is overwritten.

The rule every command that writes follows (docs/untrusted-inputs.md):

1. It never writes onto a file it reads. A dataset's images are hard links into the source trees
   they came from (KITTI, DAIR-V2X), so "a file it reads" is decided by inode, not by name: an
   output that is the same file as an input, or that lies inside an input folder, is refused.
2. It never writes onto a file it did not create. A new name is fine. An existing name is replaced
   only when the file carries this job's mark: a folder output is claimed with `.omnigen-job`
   (omnigen.ownership) and anything else in it is refused; a single file is recognised by a mark
   inside it (a PNG text chunk, a JSON key, ONNX metadata), read from its first bytes only.
3. It writes by temporary name and rename (omnigen.files.atomic_write_bytes), never by truncating
   a file in place, so even a permitted replacement cannot write through a hard link into another
   tree: the rename replaces the name, the other links keep their bytes.

The checks run before the first byte of a job is written, so a refused run leaves everything as
it was.
"""

from __future__ import annotations

import io
import os
import stat
from pathlib import Path
from typing import Callable, Iterable

from omnigen.files import atomic_write_bytes
from omnigen.untrusted import UntrustedFileError, open_regular

MARK_KEY = "omnigen"  # the PNG text chunk and ONNX metadata key that name the job which wrote a file
MARK_PREFIX_BYTES = 1 << 16  # how much of an existing file is read to find its mark


class OutputError(ValueError):
    """An output this job may not write: it names the path and why."""


def _stat(path: str | os.PathLike) -> os.stat_result | None:
    try:
        return os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return None


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether two names are one file (one inode: hard links and symbolic links count)."""
    sa, sb = _stat(a), _stat(b)
    return sa is not None and sb is not None and (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino)


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


def refuse_inputs(out: str | os.PathLike, inputs: Iterable[str | os.PathLike], job: str) -> None:
    """Refuse `out` when it is one of `inputs` (by inode), lies inside an input folder, or (for a
    folder output) holds an input file. `inputs` are the files and folders the job reads."""
    out = Path(out)
    for given in inputs:
        src = Path(given)
        if same_file(out, src):
            raise OutputError(f"{out}: is {src}, which 'omnigen {job}' reads; refusing to write onto an input "
                              "(choose another --out)")
        if src.is_dir() and _inside(out, src):
            raise OutputError(f"{out}: lies inside {src}, which 'omnigen {job}' reads; refusing to write into an "
                              "input (choose an --out outside it)")
        if out.is_dir() and _inside(src, out):  # a rerun clears its own subfolders: an input there would go
            raise OutputError(f"{out}: holds {src}, which 'omnigen {job}' reads; refusing to write into a folder "
                              "that holds an input (choose another --out)")


def check_output_file(out: str | os.PathLike, job: str, made_by_job: Callable[[Path], bool],
                      inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Check that the single file `out` may be written by `job`; returns it as a Path.

    Allowed: a new name in an existing or new folder; an existing regular file that `made_by_job`
    recognises (a rerun). Refused, naming the file: an input, a folder, a FIFO or device, a file of
    anyone else.
    """
    out = Path(out)
    refuse_inputs(out, inputs, job)
    try:
        st = os.lstat(out)
    except FileNotFoundError:
        return out
    except NotADirectoryError:
        raise OutputError(f"{out}: a parent of it is a file, not a folder") from None
    if stat.S_ISLNK(st.st_mode):
        raise OutputError(f"{out}: is a symbolic link; 'omnigen {job}' writes only files it made (choose another "
                          "--out)")
    if stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{out}: is a folder; 'omnigen {job}' writes one file here (name the file)")
    if not stat.S_ISREG(st.st_mode):
        raise OutputError(f"{out}: is not a regular file; refusing to write onto it")
    if not made_by_job(out):
        raise OutputError(f"{out}: exists and was not written by 'omnigen {job}'; refusing to overwrite it "
                          "(delete it or choose another --out)")
    return out


def read_prefix(path: Path, size: int = MARK_PREFIX_BYTES) -> bytes:
    """The first `size` bytes of a regular file (b"" for anything else or unreadable): what a mark
    is looked for in, so a check never reads a large file whole, nor waits on a FIFO."""
    try:
        with open_regular(path, max_bytes=1 << 62) as fh:
            return fh.read(size)
    except (OSError, UntrustedFileError):
        return b""


def write_output_file(out: str | os.PathLike, data: bytes, job: str, made_by_job: Callable[[Path], bool],
                      inputs: Iterable[str | os.PathLike] = ()) -> None:
    """Write a single-file output, checked again just before the rename: a command checks its
    output before its work (a refusal costs nothing), and an evaluation can take hours, in which a
    file of the user's may have appeared at that name."""
    atomic_write_bytes(check_output_file(out, job, made_by_job, inputs), data)


# -- marks in the file formats omnigen writes -----------------------------------------------------

def png_mark(job: str):
    """PNG text chunks naming the job, for PIL's `save(..., pnginfo=...)`."""
    from PIL.PngImagePlugin import PngInfo

    info = PngInfo()
    info.add_text(MARK_KEY, job)
    return info


def png_made_by(job: str) -> Callable[[Path], bool]:
    """Recognises a PNG written with `png_mark(job)`: its text chunks come before the pixels, so
    the prefix of the file holds them."""
    needle = MARK_KEY.encode() + b"\x00" + job.encode()

    def check(path: Path) -> bool:
        head = read_prefix(path)
        return head.startswith(b"\x89PNG\r\n\x1a\n") and needle in head

    return check


def jpeg_mark(job: str) -> bytes:
    """A JPEG comment naming the job, for PIL's `save(..., comment=...)`."""
    return f"{MARK_KEY}: {job}".encode()


def jpeg_made_by(job: str) -> Callable[[Path], bool]:
    needle = jpeg_mark(job)

    def check(path: Path) -> bool:
        head = read_prefix(path)
        return head.startswith(b"\xff\xd8") and needle in head

    return check


def json_made_by(job: str) -> Callable[[Path], bool]:
    """Recognises a JSON file whose first key is `"omnigen": job` (writers put it first), written
    compact (orjson, `separators=(",", ":")`) or with an indent of 2; json.dumps' default spacing
    without an indent is not recognised."""
    needles = (b'{"%s":"%s"' % (MARK_KEY.encode(), job.encode()),
               b'{\n  "%s": "%s"' % (MARK_KEY.encode(), job.encode()))

    def check(path: Path) -> bool:
        head = read_prefix(path, 4096)
        return head.startswith(needles)

    return check


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
"""What save_image writes: the two formats that carry a job's mark (a PNG text chunk, a JPEG comment)."""


def save_image(image, path: str | os.PathLike, job: str, **options) -> None:
    """Save a PIL image atomically, with `job`'s mark: PNG or JPEG by the file's suffix (anything
    else is refused: it would be PNG bytes under another format's name)."""
    path = Path(path)
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise OutputError(f"{path}: 'omnigen {job}' writes PNG or JPEG pictures; name the file .png or .jpg")
    fmt = "JPEG" if path.suffix.lower() in (".jpg", ".jpeg") else "PNG"
    buf = io.BytesIO()
    if fmt == "PNG":
        image.save(buf, format="PNG", pnginfo=png_mark(job), **options)
    else:
        image.save(buf, format="JPEG", comment=jpeg_mark(job), **options)
    atomic_write_bytes(path, buf.getvalue())


def image_made_by(job: str) -> Callable[[Path], bool]:
    """Recognises a PNG or JPEG written by `save_image(..., job)`."""
    png, jpeg = png_made_by(job), jpeg_made_by(job)
    return lambda path: png(path) or jpeg(path)
