"""`omnigen show`: the drawn pixels sit where the record's corners are, each edge in its colour,
the ignore region shaded, and the BEV footprint where the object stands on the ground; with
--instant, every view of one instant in one row, ego first, each tracked cuboid in its track's colour
in every panel, a frame without a sequence refused in one line, and a single frame drawn as before."""

from __future__ import annotations

import dataclasses
import hashlib
import math

import numpy as np
import pytest
from PIL import Image

from omnigen.cli import main
from omnigen.conventions import NEAR_PLANE, SKELETON
from omnigen.dataset import Dataset
from omnigen.draw import (BACKGROUND, CLASS_COLORS, EDGE_COLORS, PANEL_GAP, TITLE_HEIGHT, clip_segment,
                          display_scale, draw_frame, edge_segment, footprints, render_frame, render_instant,
                          track_color)
from omnigen.fakes import fake_cooperative_records, write_cooperative_dataset
from omnigen.camera import intrinsics_from_fov
from omnigen.geometry import Box3D, plane_from_height_pitch, rot_x, rot_z
from omnigen.record import FrameRecord, IgnoreRegion, ObjectRecord
from omnigen.show_command import instant_rows
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


# ---------------------------------------------------------------------------------------------
# --instant: the views of one cooperative instant
# ---------------------------------------------------------------------------------------------

SEQUENCE = "synthetic-coop-s0-q000000"
EGO_T1 = f"{SEQUENCE}-ego-t001"


@pytest.fixture(scope="module")
def coop(tmp_path_factory):
    root = tmp_path_factory.mktemp("coop") / "ds"
    write_cooperative_dataset(root, n_sequences=1, n_instants=2, width=W, height=H)
    return root


def _instant(root):
    ds = Dataset.open(root, show_progress=False)
    recs = [ds[i] for i in instant_rows(ds, SEQUENCE, 0.1)]
    return recs, [ds.path(r.image) for r in recs]


def test_instant_draws_each_view_once_in_view_order(coop, tmp_path, capsys):
    out = tmp_path / "instant.png"
    assert main(["show", str(coop), EGO_T1, "--instant", "--out", str(out)]) == 0
    line = capsys.readouterr().out
    order = [f"{SEQUENCE}-{v}-t001" for v in ("ego", "infrastructure", "aerial")]
    assert f"3 frames ({', '.join(order)})" in line, line  # the other instant's frames are not drawn
    recs, images = _instant(coop)
    assert [r.frame_id for r in recs] == order
    picture, views = render_instant(recs, images)
    panel_w = W * display_scale(W, H)
    assert [v.image.width for v in views] == [panel_w] * 3
    with Image.open(out) as im:
        assert im.size == (3 * panel_w + 2 * PANEL_GAP, views[0].image.height)
        assert np.array_equal(np.asarray(im.convert("RGB")), np.asarray(picture))

    bev = tmp_path / "bev.png"  # --bev: each view with its own BEV beside it
    assert main(["show", str(coop), EGO_T1, "--instant", "--bev", "--out", str(bev)]) == 0
    with Image.open(bev) as im:
        assert im.size == render_instant(recs, images, bev=True)[0].size and im.width > 3 * panel_w + 2 * PANEL_GAP
    inside = coop / "instant.png"  # never into the dataset
    assert main(["show", str(coop), EGO_T1, "--instant", "--out", str(inside)]) == 1 and not inside.exists()


def test_one_track_is_one_colour_in_every_view(coop):
    recs, images = _instant(coop)
    picture, views = render_instant(recs, images)
    pix = np.asarray(picture).astype(int)
    seen_in: dict[int, int] = {}
    x0 = 0
    for rec, view in zip(recs, views):
        panel = pix[view.strip:view.image.height, x0:x0 + view.image.width]
        for edge_color in EDGE_COLORS:  # tracked cuboids never take the colours by face
            assert not (panel == edge_color).all(axis=-1).any(), f"{rec.frame_id}: a face colour was drawn"
        for obj in rec.objects:
            if not obj.in_image.all():
                continue
            kp = view.frame.to_display(obj.keypoints) + [x0, view.strip]
            color = track_color(obj)
            hits = 0
            for a, b in SKELETON:
                x, y = np.round((kp[a] + kp[b]) / 2).astype(int)
                hits += (pix[y - 1:y + 2, x - 1:x + 2] == color).all(axis=-1).any()
            assert hits >= 4, f"{rec.frame_id}: track {obj.track_id} drawn in its colour on {hits} of 12 edges"
            seen_in[obj.track_id] = seen_in.get(obj.track_id, 0) + 1
        x0 += view.image.width + PANEL_GAP
    assert max(seen_in.values()) >= 2, "no track checked in two views"


def test_track_colours_are_stable_distinct_and_none_without_a_track():
    car = _record().objects[0]
    assert car.track_id is None and track_color(car) is None
    colours = [track_color(dataclasses.replace(car, track_id=t)) for t in range(1, 21)]
    assert len(set(colours)) == 20 and colours == [track_color(dataclasses.replace(car, track_id=t))
                                                   for t in range(1, 21)]
    assert all(c not in EDGE_COLORS for c in colours)


def test_untracked_objects_keep_the_colours_by_face():
    rec = _record()
    plain, by_track = render_frame(rec, None, bev=True), render_frame(rec, None, bev=True, object_color=track_color)
    below_title = slice(plain.strip, None)
    assert np.array_equal(np.asarray(plain.image)[below_title], np.asarray(by_track.image)[below_title])


# Pixel hashes of draw_frame (no corner labels: no font in them) as it drew before --instant existed,
# for the legacy frame and a cooperative (tracked) one, without and with a margin.
BEFORE = ["e13f2de1ec8376df", "5d39eb9f44f65dfc", "8b6eea2193d414e2", "79d351bfb2090a6b"]


def test_a_single_frame_is_drawn_as_before():
    coop_rec = fake_cooperative_records(n_sequences=1, n_instants=1)[0]
    now = [hashlib.sha256(draw_frame(rec, None, 2, corner_labels=False, margin=m).image.tobytes()).hexdigest()[:16]
           for rec in (_record(), coop_rec) for m in (0.0, 0.25)]
    assert now == BEFORE


def test_panels_share_one_image_height():
    recs = (fake_cooperative_records(n_sequences=1, n_instants=1, views=("ego",), width=320, height=192)
            + fake_cooperative_records(n_sequences=1, n_instants=1, views=("aerial",), width=200, height=150))
    picture, views = render_instant(recs, [None, None])
    heights = [v.frame.image.height for v in views]
    assert heights[0] == heights[1] == max(192 * display_scale(320, 192), 150 * display_scale(200, 150))
    assert picture.width == sum(v.image.width for v in views) + PANEL_GAP


@pytest.mark.parametrize("field", ["sequence", "timestamp"])
def test_a_frame_outside_any_instant_is_one_line(tmp_path, capsys, field):
    rec = fake_cooperative_records(n_sequences=1, n_instants=1, views=("ego",))[0]
    rec = dataclasses.replace(rec, timestamp=None, **({"sequence": None, "pair": None} if field == "sequence" else {}))
    root = tmp_path / "ds"
    write_cooperative_dataset(root, records=[rec])
    out = tmp_path / "x.png"
    assert main(["show", str(root), rec.frame_id, "--instant", "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"frame {rec.frame_id} has no {field}" in err and str(root) in err
    assert not out.exists()
