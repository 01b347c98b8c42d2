"""Draw one frame's cuboids, boxes and ignore regions (and its BEV) as a PNG."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path)
    p.add_argument("frame_id", help="a frame id (or the part after the source prefix when it is unique)")
    p.add_argument("--out", type=Path, default=None, help="output PNG (default: FRAME_ID.png here)")
    p.add_argument("--bev", action="store_true", help="add the bird's-eye view of the ground plane beside the image")
    p.add_argument("--scale", type=float, default=None,
                   help="display scale (default: whole-number upscale of small images)")
    p.add_argument("--margin", type=float, default=0.0,
                   help="border around the image, as a fraction of its size, to show corners outside it (e.g. 0.2)")


def run(args: argparse.Namespace) -> int:
    from omnigen.dataset import Dataset
    from omnigen.draw import render_frame

    ds = Dataset.open(args.dataset)
    frame_id = _resolve_frame_id(ds.frame_ids, args.frame_id)
    if frame_id is None:
        import difflib

        close = difflib.get_close_matches(args.frame_id, ds.frame_ids, n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        print(f"omnigen show: error: {args.dataset}: no frame {args.frame_id!r}{hint}", file=sys.stderr)
        return 1
    rec = ds.frame(frame_id)
    view = render_frame(rec, ds.path(rec.image), bev=args.bev, scale=args.scale, margin=args.margin)
    out = args.out or Path(f"{frame_id}.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    view.image.save(out)
    note = f" (image: {view.image_error})" if view.image_error else ""
    print(f"{frame_id}: {len(rec.objects)} objects, {len(rec.ignore_regions)} ignore regions -> {out}{note}")
    return 0


def _resolve_frame_id(frame_ids: list[str], wanted: str) -> str | None:
    """The frame id itself, else the one frame whose id ends with '-' + wanted (kitti-000123 for 000123)."""
    if wanted in frame_ids:
        return wanted
    matches = [f for f in frame_ids if f.endswith("-" + wanted)]
    return matches[0] if len(matches) == 1 else None
