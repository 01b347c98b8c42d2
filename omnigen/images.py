"""Reading an image that came from outside: the header's size capped before decoding, then decoded.

An image header is a claim. A 66-byte PNG can claim 13000 x 13000 pixels, and a viewer that
decodes it allocates gigabytes; a PNG cut short keeps its header, so a reader of the header only
(conversion, validation) passes it and training fails on it weeks later. So: the claimed size is
checked against MAX_IMAGE_PIXELS before any pixel is decoded, and then the whole image is decoded
(PNG also verified chunk by chunk), which is the only way to know that the pixels are all there.
Converters, `omnigen validate`, `omnigen show`, `omnigen predict` and `omnigen bev` read images
through here.
"""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path
from typing import Iterator

from PIL import Image, UnidentifiedImageError

from omnigen.untrusted import UntrustedFileError, open_regular, read_regular

MAX_IMAGE_PIXELS = 50_000_000
"""Largest image accepted (width x height). An 8K frame (7680 x 4320) is 33.2 million pixels; no
camera of a driving or roadside dataset comes near. Decoding one at the cap as RGB takes 150 MB,
which a worker of a parallel conversion can afford; beyond it a size claim is refused unread."""

MAX_IMAGE_BYTES = 256 * 2**20
"""Largest image file accepted. An uncompressed 16-bit RGB image at MAX_IMAGE_PIXELS is 300 MB, a
compressed one far less; 256 MiB keeps any real camera image and refuses a file that is not one."""

JPEG_DRAFT_SCALE = 8
"""A JPEG is decoded at 1/8 scale when checked: libjpeg still reads every entropy-coded byte (so a
truncated file fails just the same) but skips the full-size inverse DCT, a large part of the
decoding time (benchmarks/bench_image_check.py compares the check with a plain decode)."""


class ImageError(UntrustedFileError):
    """An image that cannot be used (not a regular file, too large, unreadable, cut short); names the file."""


Source = Path | str | bytes
"""A file name, or the file's bytes (read from an archive)."""


@contextlib.contextmanager
def _opened(source: Source, file: str | os.PathLike) -> Iterator[Image.Image]:
    """The image opened lazily (header parsed, no pixels), its file closed on leaving.

    PIL does not close a file object it was handed, so the file is closed here.
    """
    if isinstance(source, bytes):
        if len(source) > MAX_IMAGE_BYTES:
            raise ImageError(file, f"{len(source)} bytes, more than the {MAX_IMAGE_BYTES} allowed for an image")
        with Image.open(io.BytesIO(source)) as im:
            yield im
        return
    try:
        fh = open_regular(source, MAX_IMAGE_BYTES)
    except UntrustedFileError as exc:
        raise ImageError(file, exc.message) from None
    with fh, Image.open(fh) as im:
        yield im


def _capped_size(im: Image.Image, file: str | os.PathLike) -> tuple[int, int]:
    width, height = im.size
    if width < 1 or height < 1:
        raise ImageError(file, f"header claims an empty image ({width}x{height})")
    if width * height > MAX_IMAGE_PIXELS:
        raise ImageError(file, f"header claims {width}x{height} pixels, more than the {MAX_IMAGE_PIXELS} "
                         f"allowed (omnigen.images.MAX_IMAGE_PIXELS); not decoded")
    return width, height


_PIL_ERRORS = (OSError, SyntaxError, ValueError, EOFError, Image.DecompressionBombError)
"""The ways PIL says a file is not an image, or not a whole one."""


def _unreadable(exc: BaseException) -> str:
    if isinstance(exc, UnidentifiedImageError):  # its text names PIL's file object, not the file
        return "unreadable image: not a format PIL can identify"
    if isinstance(exc, Image.DecompressionBombError):  # PIL's own, larger cap, checked as it opens the file
        return f"unreadable image: header claims more pixels than PIL decodes; not decoded ({exc})"
    return f"unreadable image: {exc}"


def _name(source: Source, file: str | os.PathLike | None) -> str | os.PathLike:
    return file if file is not None else ("<image bytes>" if isinstance(source, bytes) else source)


def image_size(source: Source, file: str | os.PathLike | None = None) -> tuple[int, int]:
    """(width, height) from the header only, within the caps. Fast; does not prove the pixels are there."""
    file = _name(source, file)
    try:
        with _opened(source, file) as im:
            return _capped_size(im, file)
    except (FileNotFoundError, ImageError):
        raise
    except _PIL_ERRORS as exc:
        raise ImageError(file, _unreadable(exc)) from None


def check_image(source: Source, file: str | os.PathLike | None = None) -> tuple[int, int]:
    """(width, height) of an image shown to be whole: header within the caps, then fully decoded.

    A PNG is first verified (every chunk's CRC and the closing IEND: a file cut after its pixel
    data is caught here) and then decoded; a JPEG is decoded at 1/JPEG_DRAFT_SCALE. The decoded
    size must equal the header's (PIL's decoders make it so; the check guards the promise).
    """
    file = _name(source, file)
    try:
        with _opened(source, file) as im:
            width, height = _capped_size(im, file)
            if im.format != "PNG":
                _decode(im, width, height, file)
                return width, height
            im.verify()  # reads to the end: the image must be opened again to decode it
        with _opened(source, file) as im:
            _decode(im, width, height, file)
    except (FileNotFoundError, ImageError):
        raise
    except _PIL_ERRORS as exc:
        raise ImageError(file, _unreadable(exc)) from None
    return width, height


def _decode(im: Image.Image, width: int, height: int, file: str | os.PathLike) -> None:
    """Every pixel decoded (a JPEG at 1/JPEG_DRAFT_SCALE), and the result of the header's size."""
    if im.size != (width, height):
        raise ImageError(file, f"size changed between two reads: {im.size[0]}x{im.size[1]} vs {width}x{height}")
    if im.format == "JPEG":
        im.draft(im.mode, (max(1, width // JPEG_DRAFT_SCALE), max(1, height // JPEG_DRAFT_SCALE)))
    im.load()
    if im.format != "JPEG" and im.size != (width, height):
        raise ImageError(file, f"decoded {im.size[0]}x{im.size[1]}, header says {width}x{height}")


def load_rgb(path: Path | str) -> Image.Image:
    """The image decoded as RGB, its size checked against the caps before any pixel is decoded.

    The caps are ImageError; PIL's own errors propagate unchanged (a viewer shows them as they are).
    """
    with _opened(path, path) as im:
        _capped_size(im, path)
        return im.convert("RGB")


def read_rgb(path: Path | str) -> Image.Image:
    """load_rgb for a job that goes on without the image: every failure, PIL's own included, is an
    ImageError naming the file, so the caller lists it and skips the image (omnigen bev)."""
    try:
        return load_rgb(path)
    except (FileNotFoundError, ImageError):
        raise
    except _PIL_ERRORS as exc:
        raise ImageError(path, _unreadable(exc)) from None


def read_image_bytes(path: Path | str) -> tuple[bytes, tuple[int, int]]:
    """The bytes of an image file and its (width, height), the header's size within the caps.

    For a reader that decodes with another library (the detector decodes with OpenCV, as in
    training): it decodes these bytes, the ones whose header was checked, not the file read again.
    """
    try:
        data = read_regular(path, MAX_IMAGE_BYTES)
    except UntrustedFileError as exc:
        raise ImageError(path, exc.message) from None
    except OSError as exc:  # gone, or unreadable, since it was listed
        raise ImageError(path, f"cannot be read: {exc.strerror or exc}") from None
    return data, image_size(data, path)
