"""Draw one frame's cuboids, boxes and ignore regions (and its BEV) as a PNG; with --instant, every
frame of its instant (same sequence and timestamp: one world seen by each rig) side by side, each
cuboid in its track's colour, so that one object can be followed from view to view.

The picture is written to a new file or over one that show wrote before (its PNG carries show's
mark), by temporary name and rename; never into the dataset or onto the frame's image, which may
be a hard link into the source tree it came from (omnigen.outputs).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from omnigen.conventions import VIEWS
from omnigen.options import number

if TYPE_CHECKING:
    from omnigen.dataset import Dataset
    from omnigen.record import FrameRecord

MAX_SCALE = 16.0
"""Largest --scale: a whole-number upscale is what makes small images readable (the default goes
to 8); beyond 16 a pixel of the image is a block of the picture with nothing more to see."""
MAX_MARGIN = 1.0
"""Largest --margin: a border as wide as the image on each side; corners further out than that
belong to objects mostly outside the picture anyway."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path)
    p.add_argument("frame_id", help="a frame id (or the part after the source prefix when it is unique)")
    p.add_argument("--out", type=Path, default=None,
                   help="output PNG (default: FRAME_ID.png here): a new file, or one show wrote; never in the dataset")
    p.add_argument("--bev", action="store_true", help="add the bird's-eye view of the ground plane beside the image")
    p.add_argument("--scale", type=number(0.0, MAX_SCALE, lo_open=True), default=None,
                   help=f"display scale in (0, {MAX_SCALE:g}] (default: whole-number upscale of small images)")
    p.add_argument("--margin", type=number(0.0, MAX_MARGIN), default=0.0,
                   help="border around the image, as a fraction of its size, to show corners outside it (e.g. 0.2; "
                        f"at most {MAX_MARGIN:g})")
    p.add_argument("--instant", action="store_true",
                   help="draw every frame of FRAME_ID's instant (same sequence and timestamp) in one row, ordered "
                        "ego, infrastructure, aerial, each cuboid in its track's colour")


def run(args: argparse.Namespace) -> int:
    from omnigen.dataset import Dataset
    from omnigen.draw import render_frame
    from omnigen.outputs import check_output_file, image_made_by, save_image

    ds = Dataset.open(args.dataset)
    frame_id = _resolve_frame_id(ds.frame_ids, args.frame_id)
    if frame_id is None:
        import difflib

        close = difflib.get_close_matches(args.frame_id, ds.frame_ids, n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        print(f"omnigen show: error: {args.dataset}: no frame {args.frame_id!r}{hint}", file=sys.stderr)
        return 1
    rec = ds.frame(frame_id)
    if args.instant:
        return _show_instant(args, ds, rec)
    image = ds.path(rec.image)
    out = check_output_file(args.out or Path(f"{frame_id}.png"), "show", image_made_by("show"),
                            inputs=[args.dataset, image])
    view = render_frame(rec, image, bev=args.bev, scale=args.scale, margin=args.margin)
    save_image(view.image, out, "show")
    note = f" (image: {view.image_error})" if view.image_error else ""
    print(f"{frame_id}: {len(rec.objects)} objects, {len(rec.ignore_regions)} ignore regions -> {out}{note}")
    return 0


def _resolve_frame_id(frame_ids: list[str], wanted: str) -> str | None:
    """The frame id itself, else the one frame whose id ends with '-' + wanted (kitti-000123 for 000123)."""
    if wanted in frame_ids:
        return wanted
    matches = [f for f in frame_ids if f.endswith("-" + wanted)]
    return matches[0] if len(matches) == 1 else None


def _show_instant(args: argparse.Namespace, ds: "Dataset", rec: "FrameRecord") -> int:
    """Write the row of `rec`'s instant, or say in one line why the frame has none."""
    from omnigen.draw import render_instant
    from omnigen.outputs import check_output_file, image_made_by, save_image

    if rec.sequence is None or rec.timestamp is None:
        missing = "sequence" if rec.sequence is None else "timestamp"
        print(f"omnigen show: error: {args.dataset}: frame {rec.frame_id} has no {missing}; --instant draws the "
              f"frames sharing a sequence and timestamp", file=sys.stderr)
        return 1
    recs = [ds[i] for i in instant_rows(ds, rec.sequence, rec.timestamp)]
    images = [ds.path(r.image) for r in recs]
    out = check_output_file(args.out or Path(f"{rec.frame_id}-instant.png"), "show", image_made_by("show"),
                            inputs=[args.dataset, *images])
    picture, views = render_instant(recs, images, bev=args.bev, scale=args.scale, margin=args.margin)
    save_image(picture, out, "show")
    errors = [f"{r.frame_id}: {v.image_error}" for r, v in zip(recs, views) if v.image_error]
    note = f" (images: {'; '.join(errors)})" if errors else ""
    print(f"{rec.sequence} t={rec.timestamp:g} s: {len(recs)} frames ({', '.join(r.frame_id for r in recs)}), "
          f"{len({o.track_id for r in recs for o in r.objects if o.track_id is not None})} tracks -> {out}{note}")
    return 0


def instant_rows(ds: "Dataset", sequence: str, timestamp: float) -> list[int]:
    """Rows of the frames of one instant (omnigen.cooperation.instant_key), from the index's columns
    without building any record, ordered by view (in VIEWS' order: ego, infrastructure, aerial)
    and frame id."""
    from omnigen.cooperation import instant_key

    key = instant_key(sequence, timestamp)
    t = ds.table
    rows = [i for i, (q, ts) in enumerate(zip(t.sequence, t.timestamp))
            if q == sequence and not math.isnan(ts) and instant_key(q, ts) == key]
    return sorted(rows, key=lambda i: (VIEWS.index(t.view[i]), t.frame_id[i]))
