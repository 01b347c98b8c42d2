"""Geometry: corner order, flips, projection, KITTI and DAIR-V2X frames (Blender cameras: test_camera.py)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from omnigen.conventions import BOTTOM_CORNERS, FLIP_IDX, NEAR_PLANE, TOP_CORNERS
from omnigen.formats.dair import box_from_dair, boxes_from_dair
from omnigen.formats.kitti import box_from_kitti, box_to_kitti, camera_offset_from_projection, kitti_rotation
from omnigen.geometry import (
    Box3D,
    cuboid_corners,
    fit_ground,
    fit_plane,
    plane_from_height_pitch,
    project_box,
    project_boxes,
    project_points,
    rot_x,
    rot_y,
    rot_z,
    rots_z,
    self_occluded_corners,
    self_occluded_corners_batch,
)

REALDATA = Path(__file__).resolve().parents[2].parent / "shared" / "realdata"


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def random_box(rng: np.random.Generator) -> Box3D:
    center = np.array([rng.uniform(-5, 5), rng.uniform(-2, 2), rng.uniform(8, 40)])
    dims = rng.uniform(0.5, 5.0, size=3)
    return Box3D(center, dims, random_rotation(rng))


K = np.array([[720.0, 0, 619.5], [0, 720.0, 187.5], [0, 0, 1]])


def test_corner_order_follows_object_axes():
    rng = np.random.default_rng(0)
    for _ in range(50):
        box = random_box(rng)
        c = box.corners()
        along_up = (c - box.center) @ box.up
        along_fwd = (c - box.center) @ box.forward
        along_left = (c - box.center) @ box.left
        assert (along_up[list(TOP_CORNERS)] > 0).all() and (along_up[list(BOTTOM_CORNERS)] < 0).all()
        assert (along_fwd[[0, 1, 4, 5]] > 0).all() and (along_fwd[[2, 3, 6, 7]] < 0).all()
        assert (along_left[[0, 3, 4, 7]] > 0).all() and (along_left[[1, 2, 5, 6]] < 0).all()
        # 4-7 sit exactly under 0-3 along the object's up.
        np.testing.assert_allclose(c[:4] - c[4:], np.tile(box.up * box.dims[2], (4, 1)), atol=1e-12)


def test_cuboid_corners_against_a_hand_computed_cuboid():
    """The one corner function, one box and a batch, against corners written out by hand in the
    contract's order (../shared/conventions.md: 0 top front-left, 1 top front-right, 2 top
    rear-right, 3 top rear-left, 4-7 the bottom corners under them)."""
    l, w, h = 4.0, 2.0, 1.5
    center = np.array([1.0, -2.0, 10.0])
    # object x forward -> camera +z, y left -> camera -x, z up -> camera -y (a level camera
    # looking along the object's heading)
    rotation = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    fwd, left, up = rotation[:, 0] * l / 2, rotation[:, 1] * w / 2, rotation[:, 2] * h / 2
    hand = np.array([fwd + left + up, fwd - left + up, -fwd - left + up, -fwd + left + up,
                     fwd + left - up, fwd - left - up, -fwd - left - up, -fwd + left - up]) + center
    np.testing.assert_array_equal(hand[0], [0.0, -2.75, 12.0])  # top front-left: ahead, left (-x), up (-y)
    np.testing.assert_allclose(cuboid_corners(center, [l, w, h], rotation), hand, atol=1e-12)
    np.testing.assert_allclose(Box3D(center, [l, w, h], rotation).corners(), hand, atol=1e-12)
    rng = np.random.default_rng(11)
    boxes = [random_box(rng) for _ in range(9)] + [Box3D(center, [l, w, h], rotation)]
    batch = cuboid_corners(np.array([b.center for b in boxes]), np.array([b.dims for b in boxes]),
                           np.array([b.rotation for b in boxes]))
    assert batch.shape == (10, 8, 3)
    for b, corners in zip(boxes, batch):
        assert _same(b.corners(), corners)  # alone or in a batch: the same bits
    np.testing.assert_allclose(batch[-1], hand, atol=1e-12)
    assert cuboid_corners(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3))).shape == (0, 8, 3)


def test_rots_z_is_rot_z_entry_for_entry():
    yaws = np.random.default_rng(12).uniform(-7.0, 7.0, 50)
    stacked = rots_z(yaws)
    assert stacked.shape == (50, 3, 3) and rots_z([]).shape == (0, 3, 3)
    for yaw, r in zip(yaws, stacked):
        assert _same(rot_z(float(yaw)), r)


def test_fit_ground_on_a_known_plane_with_an_outlier():
    """The ground fit both converters use: bottoms of boxes on a known tilted plane plus one box
    floating a metre up; the fit finds the plane, and each refusal gives None."""
    truth = plane_from_height_pitch(1.7, math.radians(4.0), math.radians(2.0))
    rng = np.random.default_rng(13)
    centers = np.stack([rng.uniform(-8, 8, 8), np.zeros(8), rng.uniform(6, 40, 8)], axis=1)
    centers -= np.outer(truth.distance(centers), truth.normal)  # onto the plane
    up_axis = truth.normal
    boxes = []
    for i, c in enumerate(centers):
        forward = np.cross(up_axis, [1.0, 0.0, 0.0]) if i % 2 else np.cross([0.0, 0.0, 1.0], up_axis)
        forward /= np.linalg.norm(forward)
        rotation = np.stack([forward, np.cross(up_axis, forward), up_axis], axis=1)
        dims = np.array([4.0, 1.8, 1.5])
        lift = 1.0 if i == 0 else 0.0  # box 0 floats a metre above the road
        boxes.append(Box3D(c + up_axis * (dims[2] / 2 + lift), dims, rotation))
    bottoms = np.array([b.corners()[list(BOTTOM_CORNERS)] for b in boxes])
    camera_up = np.array([0.0, -1.0, 0.0])
    plane = fit_ground(bottoms, camera_up, min_objects=3, max_tilt=math.radians(15))
    assert plane is not None
    np.testing.assert_allclose(plane.normal, truth.normal, atol=2e-3)
    assert plane.offset == pytest.approx(truth.offset, abs=0.02)  # the floating box barely moves it
    assert plane.tilt(camera_up) == pytest.approx(truth.tilt(camera_up), abs=2e-3)
    # the plain least-squares plane through the same points is pulled up by the outlier
    mean = bottoms.reshape(-1, 3).mean(axis=0)
    assert abs(truth.distance(mean)) > 0.1
    assert fit_ground(bottoms, camera_up, min_objects=9, max_tilt=math.radians(15)) is None  # too few objects
    assert fit_ground(bottoms, camera_up, min_objects=3, max_tilt=math.radians(3)) is None  # tilted ~4.5 degrees
    flipped = fit_ground(bottoms, -camera_up, min_objects=3, max_tilt=math.pi)
    np.testing.assert_allclose(flipped.normal, -truth.normal, atol=2e-3)  # the normal follows `up`
    line = np.zeros((3, 4, 3))
    line[..., 0] = np.arange(12).reshape(3, 4)  # collinear: no unique plane
    assert fit_ground(line, camera_up, min_objects=3, max_tilt=math.pi) is None


def test_horizontal_flip_permutes_corners_by_flip_idx():
    rng = np.random.default_rng(1)
    width = 1242
    for _ in range(50):
        box = random_box(rng)
        # Mirror the world in x (camera frame); keep the object a proper rotation by negating its
        # left axis, which is exactly what swaps left and right corners.
        mirror = np.diag([-1.0, 1.0, 1.0])
        mirrored_rot = mirror @ box.rotation @ np.diag([1.0, -1.0, 1.0])
        mirrored = Box3D(mirror @ box.center, box.dims, mirrored_rot)
        kflip = K.copy()
        kflip[0, 2] = (width - 1) - K[0, 2]  # flipping the image maps x -> W - 1 - x
        uv, _ = project_points(K, box.corners())
        uv_m, _ = project_points(kflip, mirrored.corners())
        flipped = uv.copy()
        flipped[:, 0] = (width - 1) - flipped[:, 0]
        np.testing.assert_allclose(uv_m, flipped[list(FLIP_IDX)], atol=1e-9)


def test_projection_agrees_with_opencv():
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(-10, 10, 200), rng.uniform(-3, 3, 200), rng.uniform(1, 80, 200)])
    uv, behind = project_points(K, pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, None)
    assert not behind.any()
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)


def test_points_behind_camera_are_never_mirrored_into_the_image():
    pts = np.array([[1.0, 0.5, -5.0], [0.0, 0.0, 0.0], [0.0, 0.0, NEAR_PLANE / 2], [0.2, 0.1, 5.0]])
    uv, behind = project_points(K, pts)
    assert behind.tolist() == [True, True, True, False]
    assert np.isnan(uv[:3]).all() and np.isfinite(uv[3]).all()


def test_box_straddling_the_camera_is_clipped_not_mirrored():
    box = Box3D([0.0, 1.0, 1.0], [6.0, 2.0, 1.5], rot_y(0.0) @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]]).T)
    proj = project_box(box, K, 1240, 375)
    assert proj.behind_camera.any() and not proj.behind_camera.all()
    assert np.isnan(proj.keypoints[proj.behind_camera]).all()
    assert proj.bbox is not None
    # The in-front part fills the lower image: the box cannot come from a mirrored corner above it.
    assert proj.bbox[3] == pytest.approx(374.5)
    assert 0.0 <= proj.truncation <= 1.0


def test_bbox_and_truncation():
    # Fully inside: truncation 0 and bbox = corner extents.
    box = Box3D([0.0, 0.0, 20.0], [4.0, 1.8, 1.5], kitti_rotation(0.3))
    proj = project_box(box, K, 1240, 375)
    assert proj.truncation == pytest.approx(0.0)
    np.testing.assert_allclose(proj.bbox, [*proj.keypoints.min(0), *proj.keypoints.max(0)], atol=1e-9)
    # Half outside on the left: a square facing the camera centred on the image edge.
    edge_x = (-0.5 - K[0, 2]) * 20.0 / K[0, 0]
    box = Box3D([edge_x, 0.0, 20.0], [0.01, 2.0, 2.0], kitti_rotation(math.pi / 2))
    proj = project_box(box, K, 1240, 375)
    assert proj.truncation == pytest.approx(0.5, abs=1e-3)
    assert proj.bbox[0] == pytest.approx(-0.5)
    # Wholly outside: no bbox.
    box = Box3D([100.0, 0.0, 10.0], [4.0, 1.8, 1.5], kitti_rotation(0.0))
    assert project_box(box, K, 1240, 375).bbox is None


def test_self_occlusion_hides_corners_facing_away():
    # A box straight ahead, below the camera: top face and near face visible, far bottom hidden.
    box = Box3D([0.0, 2.0, 15.0], [4.0, 2.0, 1.5], kitti_rotation(-math.pi / 2))  # forward = +z (away)
    hidden = self_occluded_corners(box)
    # forward points away, so the rear face (corners 2, 3, 6, 7) faces the camera.
    assert not hidden[[0, 1, 2, 3]].any()  # top face seen from above
    assert not hidden[[6, 7]].any()  # rear-bottom corners on the near face
    assert hidden[[4, 5]].all()  # front-bottom corners behind the box


def test_kitti_rotation_matches_the_conventions():
    for ry in np.linspace(-math.pi, math.pi, 13):
        r = kitti_rotation(ry)
        np.testing.assert_allclose(r[:, 0], [math.cos(ry), 0, -math.sin(ry)], atol=1e-12)
        np.testing.assert_allclose(r[:, 1], [math.sin(ry), 0, math.cos(ry)], atol=1e-12)
        np.testing.assert_allclose(r[:, 2], [0, -1, 0], atol=1e-12)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
        # It is the rotation about the camera's y by ry applied to the object axes laid out in a
        # camera with ry = 0 (forward +x, left +z, up -y).
        base = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]).T
        np.testing.assert_allclose(r, rot_y(ry) @ base, atol=1e-12)


def test_kitti_label_round_trip_is_exact():
    rng = np.random.default_rng(3)
    offset = np.array([0.06, -0.0003, 0.0027])
    for _ in range(200):
        h, w, l = rng.uniform(0.5, 4, 3)
        x, y, z = rng.uniform(-20, 20), rng.uniform(0.5, 3), rng.uniform(2, 70)
        ry = rng.uniform(-math.pi, math.pi)
        back = box_to_kitti(box_from_kitti(h, w, l, x, y, z, ry, offset), offset)
        np.testing.assert_allclose(back[:6], (h, w, l, x, y, z), atol=1e-6)
        assert abs(math.remainder(back[6] - ry, 2 * math.pi)) < 1e-6


def _kitti_frames():
    root = REALDATA / "kitti" / "training"
    if not root.is_dir():
        pytest.skip(f"real KITTI frames not found at {root} (../shared/realdata is absent)")
    for label in sorted((root / "label_2").glob("*.txt")):
        calib = {}
        for line in (root / "calib" / label.name).read_text().splitlines():
            if ":" in line:
                key, values = line.split(":", 1)
                calib[key] = np.array(values.split(), dtype=np.float64)
        width, height = Image.open(root / "image_2" / f"{label.stem}.png").size
        yield label, calib["P2"].reshape(3, 4), width, height


def test_real_kitti_cars_project_onto_their_2d_boxes():
    checked = 0
    for label, P2, width, height in _kitti_frames():
        offset = camera_offset_from_projection(P2)
        np.testing.assert_allclose(P2[:, :3] @ offset, P2[:, 3], atol=1e-9)  # the 45.76 px column is K t
        assert offset[0] > 0.05  # camera 2 sits about 6 cm right of camera 0
        for line in label.read_text().splitlines():
            f = line.split()
            if f[0] != "Car":
                continue
            h, w, l, x, y, z, ry = map(float, f[8:15])
            box = box_from_kitti(h, w, l, x, y, z, ry, offset)
            proj = project_box(box, P2[:, :3], width, height)
            # The P2-matrix projection of the camera-0 corners and ours of the camera-2 box agree.
            corners0 = box_from_kitti(h, w, l, x, y, z, ry).corners()
            uv_p2 = (np.c_[corners0, np.ones(8)] @ P2.T)
            np.testing.assert_allclose(proj.keypoints, uv_p2[:, :2] / uv_p2[:, 2:], atol=1e-6)
            np.testing.assert_allclose(proj.bbox, np.array(f[4:8], dtype=float), atol=2.0)
            checked += 1
    assert checked >= 2


def test_dair_box_keeps_the_camera_pitch_and_the_heading():
    pitch = math.radians(20)
    # Virtual LiDAR (x forward, y left, z up) into a camera 7 m up, pitched down.
    lidar_to_level_cam = np.array([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]])
    r = rot_x(-pitch) @ lidar_to_level_cam
    r = np.linalg.qr(r)[0] * np.sign(np.diag(np.linalg.qr(r)[1]))
    t = r @ np.array([0.0, 0.0, -7.0])
    box = box_from_dair([30.0, 2.0, -6.2], [4.5, 1.9, 1.6], 0.0, r, t)
    up_lidar = r.T @ box.up
    np.testing.assert_allclose(up_lidar, [0, 0, 1], atol=1e-12)  # up stays the LiDAR's z
    fwd_lidar = r.T @ box.forward
    np.testing.assert_allclose(fwd_lidar, [1, 0, 0], atol=1e-12)  # yaw 0 heads along +x
    assert abs(box.up @ np.array([0, -1, 0])) < 0.99  # not the camera's -y: the pitch is kept


def test_plane_helpers():
    plane = plane_from_height_pitch(6.0, math.radians(25))
    assert plane.camera_height == pytest.approx(6.0)
    assert plane.camera_pitch == pytest.approx(math.radians(25))
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(40, 3)) * [5, 0, 5] + [0, 0, 20]
    pts = pts - np.outer(plane.distance(pts), plane.normal)
    pts[:3] += plane.normal * 2.0  # outliers the reweighting should resist
    fitted = fit_plane(pts)
    assert fitted.camera_height == pytest.approx(6.0, abs=0.05)
    assert fitted.camera_pitch == pytest.approx(math.radians(25), abs=0.01)


def test_rotations_are_proper():
    for f in (rot_x, rot_y, rot_z):
        r = f(0.7)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit for bit (NaN included), as a record written from either would be byte-identical."""
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def test_batch_projection_is_bit_identical_to_project_box():
    """project_boxes, boxes_from_dair, cuboid_corners and self_occluded_corners_batch against the
    per-box functions on random DAIR boxes under random pole cameras, with every kind of box:
    wholly inside, truncated, wholly outside, and straddling or behind the camera."""
    rng = np.random.default_rng(7)
    kinds = {"inside": 0, "truncated": 0, "outside": 0, "behind": 0}
    for _ in range(120):
        r = rot_x(-math.pi / 2 - rng.uniform(0.1, 0.5)) @ rot_z(rng.uniform(-math.pi, math.pi))  # a pitched pole camera
        t = rng.normal(0.0, 3.0, size=3)
        width, height = int(rng.integers(64, 1920)), int(rng.integers(36, 1080))
        K = np.array([[rng.uniform(300, 2500), 0, width / 2], [0, rng.uniform(300, 2500), height / 2], [0, 0, 1.0]])
        n = int(rng.integers(1, 25))
        centers_lidar = rng.uniform([-30, -40, -10], [60, 40, 4], size=(n, 3))
        lwh = rng.uniform(0.2, 12.0, size=(n, 3))
        yaw = rng.uniform(-7.0, 7.0, size=n)
        centers, rotations = boxes_from_dair(centers_lidar, yaw, r, t)
        corners = cuboid_corners(centers, lwh, rotations)
        batch = project_boxes(corners, K, width, height)
        occluded = self_occluded_corners_batch(centers, lwh, rotations)
        assert len(batch) == n
        for i in range(n):
            box = box_from_dair(centers_lidar[i], lwh[i], float(yaw[i]), r, t)
            one = project_box(box, K, width, height)
            got = batch[i]
            assert _same(box.center, centers[i]) and _same(box.rotation, rotations[i])
            assert _same(box.corners(), corners[i])
            assert _same(one.keypoints, got.keypoints)
            assert _same(one.in_image, got.in_image) and _same(one.behind_camera, got.behind_camera)
            assert (one.bbox is None) == (got.bbox is None) == (not batch.has_bbox()[i])
            if one.bbox is not None:
                assert _same(one.bbox, got.bbox)
            assert one.truncation == got.truncation
            assert _same(self_occluded_corners(box), occluded[i])
            if one.behind_camera.any():
                kinds["behind"] += 1
            elif one.in_image.all():
                kinds["inside"] += 1
            else:
                kinds["truncated" if one.bbox is not None else "outside"] += 1
    assert min(kinds.values()) >= 20, kinds  # every branch of project_box was compared


def test_batch_projection_of_no_boxes():
    K = np.array([[500.0, 0, 50], [0, 500.0, 30], [0, 0, 1]])
    empty = project_boxes(np.zeros((0, 8, 3)), K, 100, 60)
    assert len(empty) == 0 and empty.keypoints.shape == (0, 8, 2) and empty.bbox.shape == (0, 4)
