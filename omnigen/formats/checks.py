"""What an exporter checks before its first byte: that every number it writes is finite.
(Where it writes is omnigen.outputs': never into the dataset it reads, nor into a folder that
holds it.)

A record can hold finite values whose arithmetic overflows: corners at +-1e308 make a 2D box
2e308 wide, which is inf. The writers do not fail on that, each hides it its own way: orjson
writes inf and NaN as `null` (a COCO width and area of null), numpy's clip turns inf into a
plausible 1.0 in a YOLO label, Python writes the text `inf` into a KITTI label. So `omnigen
export` checks the values it is about to write and refuses, naming the frame's record file and
the field, before anything is written (tests/core/test_safety_export.py).
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Iterator

import numpy as np

from omnigen.dataset import Dataset, record_path


class NonFiniteError(ValueError):
    """An exported value that is not a finite number. Its text names the field; an exporter
    that knows the frame's record file puts that first (`in_frame`)."""


def is_finite(values: Any) -> bool:
    return bool(np.isfinite(np.asarray(values, dtype=np.float64)).all())


def non_finite(where: str, written: str, values: Any) -> NonFiniteError:
    """The error for one field: what the format would have written, and that nothing was."""
    shown = np.asarray(values, dtype=np.float64).tolist()
    return NonFiniteError(f"{where}: the {written} would be {shown}, which is not finite; refusing to export "
                          "(nothing written; check the record's values with omnigen validate)")


def in_frame(ds: Dataset, frame: int, error: NonFiniteError) -> NonFiniteError:
    """`error` prefixed with the frame's record file, the file a user opens to fix it."""
    return NonFiniteError(f"{record_path(ds.root, ds.table.frame_id[frame])}: {error}")


@contextmanager
def naming_frame(ds: Dataset, frame: int) -> Iterator[None]:
    """A NonFiniteError raised in the block (by formats.kitti's text, say) names the frame's record file."""
    try:
        yield
    except NonFiniteError as exc:
        raise in_frame(ds, frame, exc) from None


def check_frame_values(ds: Dataset, frame: int, field: str, written: str, values: Any) -> None:
    """Refuse one frame's field (K, an ignore region, ...) unless every value in it is finite."""
    if not is_finite(values):
        raise in_frame(ds, frame, non_finite(field, written, values))


def check_object_columns(ds: Dataset, columns: dict[str, tuple[str, np.ndarray]],
                         keep: np.ndarray | None = None) -> None:
    """Refuse the first object (in dataset order) whose row of any column holds a non-finite value.

    `columns` maps the record field a value comes from to what the format writes from it (its
    name, and an (N, ...) array with one row per object of ds.objects, values the format leaves
    out already zeroed); `keep` masks the objects the export writes. Vectorised: a
    300,000-object dataset costs a few array passes, not a walk over the written dict.
    """
    first: tuple[int, str] | None = None
    for field, (_, values) in columns.items():
        bad = ~np.isfinite(values).all(axis=tuple(range(1, values.ndim)))
        if keep is not None:
            bad &= keep
        rows = np.flatnonzero(bad)
        if len(rows) and (first is None or rows[0] < first[0]):
            first = (int(rows[0]), field)
    if first is None:
        return
    row, field = first
    frame = int(ds.objects.frame[row])
    written, values = columns[field]
    raise in_frame(ds, frame, non_finite(f"objects[{row - int(ds.offsets[frame])}].{field}", written, values[row]))
