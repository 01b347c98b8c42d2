"""Reading back a rendered dataset folder, for the render tests (sequences, cooperative views, frames)."""

from __future__ import annotations

import json
from pathlib import Path

from omnigen.record import FrameRecord

SUBS = ("records", "images", "depth", "instance")


def read_records(root: Path) -> list[FrameRecord]:
    """Every record under root/records, in file-name order."""
    return [FrameRecord.from_dict(json.loads(p.read_text())) for p in sorted((root / "records").glob("*.json"))]


def same_files(a: Path, b: Path) -> None:
    """Every frame's files and the manifest (the index holds file times) byte for byte."""
    assert (a / "manifest.json").read_bytes() == (b / "manifest.json").read_bytes()
    for sub in SUBS:
        names = sorted(p.name for p in (a / sub).iterdir())
        assert names == sorted(p.name for p in (b / sub).iterdir()), sub
        for name in names:
            assert (a / sub / name).read_bytes() == (b / sub / name).read_bytes(), (sub, name)


def masks_inside_cuboids(root: Path) -> int:
    """tests/rigs/test_render.py's rule over every record of a folder: >= 99% of each object's
    instance mask lies inside its cuboid's projected hull grown by 1 px; the objects checked."""
    import numpy as np
    import shapely

    from omnigen.geometry import silhouette
    from omnigen.rigs.render import read_instance_png

    checked = 0
    for rec in read_records(root):
        inst = read_instance_png(root / rec.synthetic.instance)
        v, u = np.mgrid[0:rec.height, 0:rec.width]
        for o in rec.objects:
            mask = inst == o.instance_id
            hull = silhouette(o.box.corners(), rec.K).buffer(1.0)
            pts = shapely.points(np.column_stack([u[mask], v[mask]]).astype(float))
            assert shapely.contains(hull, pts).mean() >= 0.99, (rec.frame_id, o.instance_id)
            checked += 1
    return checked
