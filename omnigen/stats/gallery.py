"""The report's gallery: a few frames drawn with their cuboids beside their bird's-eye views.

Frames are picked round-robin over the (source, view) groups, so a merged dataset shows each of
its kinds of camera before it shows two of one; within a group the pick is random but seeded, so
a report rebuilt from the same dataset shows the same frames. Frames with objects are preferred.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from omnigen.conventions import SOURCES, VIEWS
from omnigen.dataset import Dataset
from omnigen.draw import display_scale, render_frame
from omnigen.outputs import save_image

JOB = "stats"

GALLERY_WIDTH = 720
"""Image panels wider than this are scaled down in the gallery (`omnigen show` keeps full size)."""

GALLERY_MIN_SIDE = 64
"""Frames whose image is narrower or shorter than this many pixels are not shown: a thumbnail or a
generated stand-in (the 96x54 DAIR-V2X-C and 124x38 KITTI trees omnigen.converters' fixtures make
for tests and the demo) drawn beside camera frames reads as data it is not. The page counts them."""


def too_small(ds: Dataset) -> np.ndarray:
    """Per frame, whether its image is under GALLERY_MIN_SIDE on a side."""
    return np.minimum(np.asarray(ds.table.width), np.asarray(ds.table.height)) < GALLERY_MIN_SIDE


def pick_gallery(ds: Dataset, n: int, seed: int = 0) -> list[int]:
    """Indices of up to `n` frames, one per (source, view) group in turn (frames of images too
    small to look at left out: `too_small`)."""
    if n <= 0 or len(ds) == 0:
        return []
    rng = np.random.default_rng(seed)
    counts = np.diff(ds.offsets)
    order = {s: i for i, s in enumerate(SOURCES)}, {v: i for i, v in enumerate(VIEWS)}
    small = too_small(ds)
    groups: dict[tuple[str, str], list[int]] = {}
    for i, key in enumerate(zip(ds.table.source, ds.table.view)):
        if not small[i]:
            groups.setdefault(key, []).append(i)
    queues = []
    for key in sorted(groups, key=lambda k: (order[0].get(k[0], 99), k[0], order[1].get(k[1], 99), k[1])):
        idx = np.asarray(groups[key])
        rng.shuffle(idx)
        with_objects = idx[counts[idx] > 0]
        queues.append(list(np.concatenate([with_objects, idx[counts[idx] == 0]])))
    picked: list[int] = []
    while len(picked) < n and any(queues):
        for q in queues:
            if q and len(picked) < n:
                picked.append(int(q.pop(0)))
    return picked


def write_gallery(ds: Dataset, out: Path, n: int, seed: int = 0) -> list[dict[str, Any]]:
    """Draw the picked frames into out/gallery/; returns their entries for stats.json."""
    entries = []
    for i in pick_gallery(ds, n, seed):
        rec = ds[i]
        scale = GALLERY_WIDTH / rec.width if rec.width > GALLERY_WIDTH else display_scale(rec.width, rec.height, 640)
        view = render_frame(rec, ds.path(rec.image), bev=True, scale=scale)
        rel = f"gallery/{rec.frame_id}.png"
        save_image(view.image, out / rel, JOB, optimize=False)  # by temporary name and rename
        entries.append({"frame_id": rec.frame_id, "source": rec.source, "view": rec.view, "file": rel,
                        "objects": len(rec.objects), "width": view.image.width, "height": view.image.height,
                        "image_error": view.image_error})
    return entries
