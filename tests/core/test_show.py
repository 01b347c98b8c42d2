"""`omnigen show`: the drawn pixels sit where the record's corners are, each edge in its colour,
the ignore region shaded, and the BEV footprint where the object stands on the ground."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from omnigen.cli import main
from omnigen.conventions import NEAR_PLANE, SKELETON
from omnigen.dataset import Dataset
from omnigen.draw import (BACKGROUND, CLASS_COLORS, EDGE_COLORS, TITLE_HEIGHT, clip_segment, display_scale,
                          edge_segment, footprints, render_frame)
from omnigen.camera import intrinsics_from_fov
from omnigen.geometry import Box3D, plane_from_height_pitch, rot_x, rot_z
from omnigen.record import FrameRecord, IgnoreRegion, ObjectRecord
from omnigen.writer import DatasetWriter

W, H = 320, 192
FRAME = "kitti-000042"
WORLD_XY = (2.0, 12.0)  # metres right of and ahead of the camera's foot
IGNORE = [6.0, 6.0, 60.0, 40.0]


def _record() -> FrameRecord:
    """One car 12 m ahead and 2 m right of a camera 3 m up (a van's roof), pitched 12 degrees down."""
    height, pitch = 3.0, math.radians(12)
    plane = plane_from_height_pitch(height, pitch)
    world_to_cam = rot_x(pitch) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    dims = np.array([4.2, 1.8, 1.5])
    center = world_to_cam @ np.array([WORLD_XY[0], WORLD_XY[1], -height + dims[2] / 2])
    K = intrinsics_from_fov(math.radians(70), W, H)
    car = ObjectRecord.from_box("car", 1, Box3D(center, dims, world_to_cam @ rot_z(0.6)), K, W, H, occlusion_level=0)
    assert car.in_image.all()
    return FrameRecord(frame_id=FRAME, source="kitti", view="ego", image=f"images/{FRAME}.png", width=W, height=H,
                       K=K, objects=[car], ignore_regions=[IgnoreRegion(np.array(IGNORE), "DontCare")],
                       ground_plane=plane, camera_height=height, camera_pitch=pitch)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("show") / "ds"
    (root / "images").mkdir(parents=True)
    rec = _record()
    Image.new("RGB", (W, H), (0, 0, 0)).save(root / rec.image)
    writer = DatasetWriter(root, durable=False)
    writer.write(rec)
    writer.finalize(show_progress=False)
    return root


def _point_segment_distance(p, a, b) -> float:
    ab, ap = b - a, p - a
    t = np.clip(ap @ ab / max(ab @ ab, 1e-12), 0, 1)
    return float(np.linalg.norm(ap - t * ab))


@pytest.mark.parametrize("margin", [0.0, 0.25])
def test_show_draws_corners_edges_and_ignore_regions_where_they_are(dataset, tmp_path, margin):
    out = tmp_path / "frame.png"
    assert main(["show", str(dataset), FRAME, "--out", str(out), "--margin", str(margin)]) == 0
    rec = Dataset.open(dataset, show_progress=False).frame(FRAME)
    pix = np.asarray(Image.open(out).convert("RGB")).astype(int)
    s = display_scale(W, H)
    offset = np.array([round(margin * W * s), round(margin * H * s) + TITLE_HEIGHT])
    assert pix.shape[:2] == (H * s + 2 * (offset[1] - TITLE_HEIGHT) + TITLE_HEIGHT, W * s + 2 * offset[0])

    def at(xy):
        return (np.asarray(xy) + 0.5) * s - 0.5 + offset

    obj = rec.objects[0]
    kp = at(obj.keypoints)
    for j, (x, y) in enumerate(kp):  # a corner marker covers each keypoint
        assert pix[int(round(y)), int(round(x))].sum() > 150, f"nothing drawn at corner {j}"

    checked = {0: 0, 1: 0, 2: 0}  # top, bottom, vertical edges whose colour was checked
    for e, (a, b) in enumerate(SKELETON):
        mid = (kp[a] + kp[b]) / 2
        others = [_point_segment_distance(mid, kp[c], kp[d]) for f, (c, d) in enumerate(SKELETON) if f != e]
        if min(others) < 5 or min(np.linalg.norm(kp - mid, axis=1)) < 12:
            continue  # crossed by another edge or under a corner label: colour ambiguous
        x, y = np.round(mid).astype(int)
        window = pix[y - 1:y + 2, x - 1:x + 2].reshape(-1, 3)
        assert (window == EDGE_COLORS[e]).all(axis=1).any(), f"edge {a}-{b} is not drawn in its colour at {mid}"
        checked[e // 4] += 1
    assert all(checked.values()), f"too few unambiguous edges to check: {checked}"

    (x1, y1), (x2, y2) = at(np.reshape(IGNORE, (2, 2)))
    region = pix[int(y1) + 3:int(y2) - 2, int(x1) + 3:int(x2) - 2].reshape(-1, 3)
    assert ((region[:, 0] > region[:, 1] + 20) & (region[:, 0] > region[:, 2] + 20)).mean() > 0.9  # shaded red
    bx1, by1, bx2, by2 = obj.bbox
    far = at([0.5 * (bx1 + 0), H - 3])  # left of and below the car, outside the ignore region
    assert far[0] < at([bx1, 0])[0] - 4
    assert (pix[int(far[1]), int(far[0])] == 0).all(), "the image must stay untouched away from the labels"


def test_bev_footprint_sits_where_the_object_stands(dataset, tmp_path):
    ds = Dataset.open(dataset, show_progress=False)
    rec = ds.frame(FRAME)
    fp = footprints(rec)
    np.testing.assert_allclose(fp[0].mean(axis=0), WORLD_XY, atol=1e-9)
    view = render_frame(rec, ds.path(rec.image), bev=True)
    assert view.bev is not None and view.image.width == view.frame.image.width + view.bev.image.width
    pix = np.asarray(view.image).astype(int)
    x, y = view.bev.to_display(np.array(WORLD_XY)) + np.array(view.bev_origin)
    inside = pix[int(round(y)), int(round(x))]
    bg = np.array(BACKGROUND)
    car = np.array(CLASS_COLORS["car"])
    # Filled with the class colour (alpha 150 of 255) over the seen-ground wedge (white, alpha 28):
    # the car is wholly in the image, so its footprint lies on ground the camera sees.
    wedge = bg + (255 - bg) * 28 / 255
    np.testing.assert_allclose(inside, wedge + (car - wedge) * 150 / 255, atol=3)
    empty = view.bev.to_display(np.array([-WORLD_XY[0] * 3, WORLD_XY[1] * 0.5])) + np.array(view.bev_origin)
    assert np.abs(pix[int(empty[1]), int(empty[0])] - car).sum() > 100

    out = tmp_path / "bev.png"
    assert main(["show", str(dataset), FRAME, "--bev", "--out", str(out)]) == 0
    with Image.open(out) as im:
        assert im.size == view.image.size


def test_show_finds_frames_by_suffix_and_names_missing_ones(dataset, tmp_path, capsys):
    out = tmp_path / "x.png"
    assert main(["show", str(dataset), "000042", "--out", str(out)]) == 0 and out.exists()
    assert main(["show", str(dataset), "kitti-000043", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "no frame 'kitti-000043'" in err and "did you mean kitti-000042" in err


def test_show_draws_labels_when_the_image_does_not_open(dataset, tmp_path, capsys):
    broken = tmp_path / "ds"
    import shutil

    shutil.copytree(dataset, broken)
    (broken / "images" / f"{FRAME}.png").write_bytes(b"garbage")
    assert main(["show", str(broken), FRAME, "--out", str(tmp_path / "y.png")]) == 0
    assert "image: UnidentifiedImageError" in capsys.readouterr().out
    assert (tmp_path / "y.png").exists()


def test_edges_are_cut_at_the_near_plane():
    K = intrinsics_from_fov(math.radians(90), W, H)
    p, q = np.array([1.0, 0.5, -2.0]), np.array([1.0, 0.5, 8.0])
    kp_q = (K @ q)[:2] / q[2]
    seg = edge_segment(p, q, np.array([np.nan, np.nan]), kp_q, K)
    cut = np.array([1.0, 0.5, NEAR_PLANE])
    np.testing.assert_allclose(seg[0], (K @ cut)[:2] / NEAR_PLANE)
    np.testing.assert_allclose(seg[1], kp_q)
    assert edge_segment(p, p - 1, kp_q, kp_q, K) is None


def test_segments_are_clipped_to_a_rectangle():
    np.testing.assert_allclose(clip_segment(np.array([[-100.0, 50], [500, 50]]), (0, 0), (320, 192)),
                               [[0, 50], [320, 50]])
    assert clip_segment(np.array([[-100.0, -5], [500, -5]]), (0, 0), (320, 192)) is None
    assert clip_segment(np.array([[np.nan, 0], [5, 5]]), (0, 0), (320, 192)) is None


@pytest.mark.parametrize("bev", [False, True])
def test_the_colour_key_is_whole_at_any_width(bev):
    """At 640 px without its BEV the key did not fit beside a long title and "top" was dropped:
    the strip takes a second row instead, and every entry of the key is drawn."""
    from dataclasses import replace

    from omnigen.draw import LEGEND

    rec = replace(_record(), frame_id="synthetic-drone-s0-000000", source="synthetic", view="aerial")
    view = render_frame(rec, None, bev=bev, scale=2.0)
    assert view.frame_origin == (0, view.strip)
    assert view.strip == (TITLE_HEIGHT if bev else 2 * TITLE_HEIGHT)
    strip = np.asarray(view.image)[:view.strip].reshape(-1, 3)
    for label, colour in LEGEND:
        assert (np.abs(strip.astype(int) - colour).sum(axis=1) < 30).sum() > 5, label
