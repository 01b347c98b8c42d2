"""The report's health section: what in a dataset looks wrong, with examples to go and look at.

Validation (`omnigen validate`) rejects what breaks the contract; these checks flag what obeys it
and is still probably a mistake: an object none of whose corners is in the image (legal for a
close truck, suspicious in bulk), a 2D box thinner than a pixel, a 3D box thinner than a sheet of
card, a "pedestrian" four metres tall, a frame with nothing in it, an image that does not open.

The object checks are vectorised over the columns. The image check opens every image's header
with PIL (no decoding), which costs a file open per frame; it is timed on its own and can be
turned off (`omnigen stats --no-check-images`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from omnigen.conventions import FINE_CLASSES
from omnigen.dataset import Dataset
from omnigen.images import image_size
from omnigen.priors import FAR_SIGMA, dims_z_scores
from omnigen.progress import progress
from omnigen.stats.compute import rnd

DEGENERATE_PX = 1.0
"""A 2D box narrower or shorter than this (pixels) cannot be learned or scored."""
DEGENERATE_M = 0.05
"""A 3D box with a dimension under this (metres) is flat: no road user or cone is that thin."""
MAX_EXAMPLES = 20


def _object_examples(ds: Dataset, rows: np.ndarray, detail: list[str], limit: int) -> list[dict[str, Any]]:
    o = ds.objects
    return [{"frame_id": ds.table.frame_id[int(o.frame[r])], "instance_id": int(o.instance_id[r]),
             "category": FINE_CLASSES[int(o.category[r])], "detail": text}
            for r, text in zip(rows[:limit].tolist(), detail)]


def _check(name: str, title: str, unit: str, count: int, examples: list[dict[str, Any]],
           **extra: Any) -> dict[str, Any]:
    return {"name": name, "title": title, "unit": unit, "count": int(count), "examples": examples, **extra}


def object_checks(ds: Dataset, sigma: float = FAR_SIGMA, limit: int = MAX_EXAMPLES) -> list[dict[str, Any]]:
    """Checks over the object and frame columns (fast: no file is opened)."""
    o = ds.objects
    checks = []

    outside = np.flatnonzero(~o.in_image.any(axis=1))
    checks.append(_check(
        "corners_all_outside", "Objects with every corner outside the image", "objects", len(outside),
        _object_examples(ds, outside, [f"bbox {_box(o.bbox[r])}, truncation {o.truncation[r]:.2f}"
                                       for r in outside[:limit]], limit)))

    w, h = o.bbox[:, 2] - o.bbox[:, 0], o.bbox[:, 3] - o.bbox[:, 1]
    flat2d = (w < DEGENERATE_PX) | (h < DEGENERATE_PX)
    flat3d = (o.dims < DEGENERATE_M).any(axis=1)
    degenerate = np.flatnonzero(flat2d | flat3d)
    details = [(f"2D box {w[r]:.2f} x {h[r]:.2f} px" if flat2d[r] else "") +
               ("; " if flat2d[r] and flat3d[r] else "") +
               (f"3D dims {_dims(o.dims[r])} m" if flat3d[r] else "") for r in degenerate[:limit]]
    checks.append(_check(
        "degenerate_boxes", f"Degenerate boxes (2D side < {DEGENERATE_PX:g} px or 3D side < {DEGENERATE_M:g} m)",
        "objects", len(degenerate), _object_examples(ds, degenerate, details, limit),
        boxes_2d=int(flat2d.sum()), boxes_3d=int(flat3d.sum())))

    z = dims_z_scores(o.category, o.dims)
    far = np.flatnonzero((np.abs(z) > sigma).any(axis=1))
    details = [f"l w h {_dims(o.dims[r])} m, {np.abs(z[r]).max():.1f} sigma from the prior" for r in far[:limit]]
    by_class = np.bincount(o.category[far].astype(np.int64), minlength=len(FINE_CLASSES))
    checks.append(_check(
        "dims_outside_priors", f"Dimensions more than {sigma:g} sigma from their class prior", "objects", len(far),
        _object_examples(ds, far, details, limit),
        by_class={c: int(n) for c, n in zip(FINE_CLASSES, by_class.tolist()) if n}))

    empty = np.flatnonzero(np.diff(ds.offsets) == 0)
    checks.append(_check(
        "frames_without_objects", "Frames with no objects", "frames", len(empty),
        [{"frame_id": ds.table.frame_id[i], "detail": f"{ds.table.source[i]}, {ds.table.view[i]}"}
         for i in empty[:limit].tolist()]))
    return checks


def _open_header(path: str) -> tuple[str, tuple[int, int] | None]:
    """('ok' | error text, size): parses the header only, through omnigen.images' guarded opener
    (a regular file within the size caps: a FIFO or a device in a dataset is reported, not waited on)."""
    try:
        return "ok", image_size(path)
    except Exception as exc:  # noqa: BLE001 - any failure to open is what this check reports
        return f"{type(exc).__name__}: {exc}".splitlines()[0][:200], None


def image_checks(ds: Dataset, limit: int = MAX_EXAMPLES, workers: int = 2,
                 show_progress: bool = True) -> list[dict[str, Any]]:
    """Open every image's header: report the ones that fail and the ones whose size disagrees with the record."""
    t = ds.table
    paths = [str(ds.path(p)) for p in t.image]
    with ThreadPoolExecutor(workers) as pool:
        results = list(progress(pool.map(_open_header, paths, chunksize=256), desc="image headers", total=len(paths),
                                disable=not show_progress))
    bad, wrong = [], []
    for i, (status, size) in enumerate(results):
        if size is None:
            bad.append({"frame_id": t.frame_id[i], "image": t.image[i], "detail": status})
        elif size != (int(t.width[i]), int(t.height[i])):
            wrong.append({"frame_id": t.frame_id[i], "image": t.image[i],
                          "detail": f"image is {size[0]}x{size[1]}, record says {t.width[i]}x{t.height[i]}"})
    return [
        _check("images_unreadable", "Images that fail to open", "frames", len(bad), bad[:limit], checked=len(paths)),
        _check("image_size_mismatch", "Images whose size differs from the record", "frames", len(wrong), wrong[:limit],
               checked=len(paths)),
    ]


def check_health(ds: Dataset, sigma: float = FAR_SIGMA, check_images: bool = True, limit: int = MAX_EXAMPLES,
                 show_progress: bool = True) -> dict[str, Any]:
    """The health section of stats.json: every check with its count and up to `limit` examples."""
    checks = object_checks(ds, sigma, limit)
    if check_images:
        checks += image_checks(ds, limit, show_progress=show_progress)
    return {"checks": checks, "images_checked": check_images, "problems": sum(c["count"] for c in checks),
            "thresholds": {"degenerate_px": DEGENERATE_PX, "degenerate_m": DEGENERATE_M, "prior_sigma": sigma},
            "example_limit": limit}


def _box(b: np.ndarray) -> str:
    return "[" + ", ".join(f"{rnd(v, 5):g}" for v in b) + "]"


def _dims(d: np.ndarray) -> str:
    return " ".join(f"{v:.2f}" for v in d)
