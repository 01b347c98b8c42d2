"""Issue 6: the Cycles backend agrees with the raster backend (tiny city, tiny image, few samples).

One frame rendered by both: the instance masks agree (mean per-object IoU >= 0.95), the Cycles
masks lie inside their projected cuboids (>= 99% within the hull grown by 1 px) and its depth is
camera z like the raster backend's.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import shapely

from omnigen.checks import check_dataset
from omnigen.geometry import silhouette
from omnigen.record import FrameRecord

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
pytest.importorskip("bpy", reason="bpy not installed")
pytest.importorskip("scenes.raster_backend", reason="pyrender/PyOpenGL not installed")

W, H = 160, 120
SEED = 5


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    from rigs.render import RenderJob, Renderer

    root = tmp_path_factory.mktemp("cycles")
    out = {}
    for backend in ("raster", "cycles"):
        job = RenderJob(rig="pole", frames=1, out=root / backend, seed=SEED, scene="tiny", width=W, height=H,
                        backend=backend, quality="preview")
        Renderer(job).run(show_progress=False)
        out[backend] = root / backend
    return out


def _load(root):
    from rigs.render import read_depth_exr, read_instance_png

    rec = FrameRecord.from_dict(json.loads(next((root / "records").glob("*.json")).read_text()))
    return rec, read_instance_png(root / rec.synthetic.instance), read_depth_exr(root / rec.synthetic.depth)


def test_cycles_and_raster_masks_agree(both):
    rr, ri, rd = _load(both["raster"])
    cr, ci, cd = _load(both["cycles"])
    assert np.array_equal(rr.K, cr.K) and rr.camera_height == cr.camera_height  # the same camera
    ids = sorted((set(np.unique(ri)) | set(np.unique(ci))) - {0})
    ious = []
    for i in ids:
        a, b = ri == i, ci == i
        if max(a.sum(), b.sum()) < 16:
            continue  # a few pixels: left out of the annotations too
        ious.append((a & b).sum() / (a | b).sum())
    assert len(ious) >= 3
    assert np.mean(ious) >= 0.95, ious
    hit = np.isfinite(rd) & np.isfinite(cd) & (ri == ci) & (ri > 0)
    assert np.median(np.abs(rd[hit] - cd[hit]) / rd[hit]) < 1e-3  # camera z in both


def test_cycles_masks_inside_projected_cuboids_and_valid(both):
    rec, inst, _ = _load(both["cycles"])
    v, u = np.mgrid[0:H, 0:W]
    assert rec.objects
    for o in rec.objects:
        mask = inst == o.instance_id
        hull = silhouette(o.box.corners(), rec.K).buffer(1.0)
        inside = shapely.contains(hull, shapely.points(np.column_stack([u[mask], v[mask]]).astype(float))).mean()
        assert inside >= 0.99, (o.instance_id, inside)
    n, problems = check_dataset(both["cycles"])
    assert n == 1 and problems == []
    from PIL import Image

    with Image.open(both["cycles"] / rec.image) as img:
        assert img.size == (W, H) and img.mode == "RGB" and np.asarray(img).std() > 2
