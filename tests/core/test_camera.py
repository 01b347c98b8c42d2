"""The core camera (omnigen/camera.py): the one axis flip, projection through geometry's code,
the Blender and OpenGL conversions. Plain numpy: no renderer needed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnigen.camera import (
    OPENCV_TO_OPENGL,
    Camera,
    blender_from_intrinsics,
    intrinsics_from_blender,
    intrinsics_from_fov,
    world_to_opencv_camera,
)
from omnigen.geometry import project_points, rot_x, rot_z

W, H = 640, 480


def _camera() -> Camera:
    """A camera at (2, -10, 3) looking along world +y, pitched 10 degrees down, rolled not at all."""
    pitch = math.radians(10)
    forward = np.array([0.0, math.cos(pitch), -math.sin(pitch)])
    right = np.array([1.0, 0.0, 0.0])
    R = np.stack([right, np.cross(forward, right), forward])
    center = np.array([2.0, -10.0, 3.0])
    K = np.array([[500.0, 0.0, 321.5], [0.0, 510.0, 238.0], [0.0, 0.0, 1.0]])
    return Camera(K, R, -R @ center, W, H)


def test_the_flip_is_its_own_inverse_and_a_proper_rotation():
    np.testing.assert_array_equal(OPENCV_TO_OPENGL @ OPENCV_TO_OPENGL, np.eye(3))
    assert np.linalg.det(OPENCV_TO_OPENGL) == pytest.approx(1.0)  # a rotation (180 degrees about x), no mirror
    # OpenCV's forward (+z) and down (+y) are OpenGL's -z and -y.
    np.testing.assert_array_equal(OPENCV_TO_OPENGL @ [0.0, 0.0, 1.0], [0.0, 0.0, -1.0])
    np.testing.assert_array_equal(OPENCV_TO_OPENGL @ [0.0, 1.0, 0.0], [0.0, -1.0, 0.0])
    with pytest.raises(ValueError):
        OPENCV_TO_OPENGL[0, 0] = 2.0  # one constant, shared: nobody may change it in place


def test_blender_pose_round_trip():
    cam = _camera()
    with pytest.raises(ValueError, match="square pixels"):  # fx != fy: Blender has one focal length ...
        cam.blender_settings()
    # ... but the pose alone goes there and back exactly (the flip applied twice).
    R, t = world_to_opencv_camera(cam.blender_matrix_world())
    np.testing.assert_allclose(R, cam.R, atol=1e-12)
    np.testing.assert_allclose(t, cam.t, atol=1e-12)
    # Blender's camera looks down its own -z: the matrix_world's third column points backwards.
    np.testing.assert_allclose(cam.blender_matrix_world()[:3, 2], -cam.R[2], atol=1e-12)
    np.testing.assert_allclose(cam.blender_matrix_world()[:3, 3], [2.0, -10.0, 3.0], atol=1e-12)


def test_blender_lens_sensor_round_trip():
    K_b = intrinsics_from_blender(35.0, 36.0, W, H, shift_x=0.01, shift_y=-0.02)
    assert K_b[0, 0] == pytest.approx(35 / 36 * 640)
    assert K_b[0, 2] == pytest.approx(320 - 0.5 - 0.01 * 640)
    assert K_b[1, 2] == pytest.approx(240 - 0.5 - 0.02 * 640)
    back = blender_from_intrinsics(K_b, W, H)
    assert back["lens"] == pytest.approx(35.0) and back["sensor_width"] == 36.0
    assert back["shift_x"] == pytest.approx(0.01) and back["shift_y"] == pytest.approx(-0.02)
    np.testing.assert_allclose(intrinsics_from_blender(back["lens"], back["sensor_width"], W, H,
                                                       back["shift_x"], back["shift_y"]), K_b, atol=1e-12)
    # A portrait image: Blender's AUTO fit measures the sensor along the longer side (height).
    K_p = intrinsics_from_blender(50.0, 36.0, 480, 640)
    assert K_p[0, 0] == pytest.approx(50 / 36 * 640)
    # The Camera's own conversions are the same numbers, both ways.
    R = rot_x(-math.pi / 2)  # any pose
    cam = Camera(K_b, R, [0.0, 1.0, 2.0], W, H)
    assert cam.blender_settings() == blender_from_intrinsics(K_b, W, H)
    again = Camera.from_blender(cam.blender_matrix_world(), width=W, height=H, **cam.blender_settings())
    np.testing.assert_allclose(again.K, cam.K, atol=1e-12)
    np.testing.assert_allclose(again.R, cam.R, atol=1e-12)
    np.testing.assert_allclose(again.t, cam.t, atol=1e-12)


def test_blender_camera_looking_north():
    # A Blender camera at (0, -10, 2) looking along +Y (rotated 90 degrees about X) sees the world
    # point (0, 0, 2) straight ahead, 10 m away, and world +Z up as image up (OpenCV -y).
    m = np.eye(4)
    m[:3, :3] = rot_x(math.pi / 2)
    m[:3, 3] = [0.0, -10.0, 2.0]
    r, t = world_to_opencv_camera(m)
    np.testing.assert_allclose(r @ np.array([0.0, 0.0, 2.0]) + t, [0, 0, 10], atol=1e-12)
    np.testing.assert_allclose(r @ np.array([0, 0, 1.0]), [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(r @ np.array([1.0, 0, 0]), [1, 0, 0], atol=1e-12)
    cam = Camera.from_blender(m, lens=36.0, width=W, height=H)  # f = 640: a 53 degree view
    uv, behind = cam.project([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0]])
    assert not behind.any()
    np.testing.assert_allclose(uv, [[319.5, 239.5], [319.5 + 64.0, 239.5]], atol=1e-9)


def test_projection_on_known_numbers():
    cam = _camera()
    # Points given in the camera frame, moved to the world: X_world = R^T (X_cam - t).
    X_cam = np.array([[0.0, 0.0, 10.0], [1.0, -2.0, 5.0], [-3.0, 1.5, 20.0], [0.0, 0.0, -4.0]])
    world = (X_cam - cam.t) @ cam.R
    np.testing.assert_allclose(cam.to_camera(world), X_cam, atol=1e-12)
    uv, behind = cam.project(world)
    # by hand: u = fx x / z + cx, v = fy y / z + cy
    expected = np.array([[321.5, 238.0], [500 * 0.2 + 321.5, 510 * -0.4 + 238.0],
                         [500 * -0.15 + 321.5, 510 * 0.075 + 238.0]])
    np.testing.assert_allclose(uv[:3], expected, atol=1e-9)
    assert behind.tolist() == [False, False, False, True] and np.isnan(uv[3]).all()
    ref_uv, ref_behind = project_points(cam.K, X_cam)
    np.testing.assert_array_equal(behind, ref_behind)
    np.testing.assert_allclose(uv, ref_uv, atol=1e-9)
    np.testing.assert_allclose(cam.center, [2.0, -10.0, 3.0], atol=1e-12)


def test_gl_view_puts_points_in_front_at_negative_z():
    cam = _camera()
    V = cam.gl_view()
    ahead = cam.center + 7.0 * cam.R[2]  # 7 m along the optical axis
    above = cam.center + 7.0 * cam.R[2] - 2.0 * cam.R[1]  # and 2 m up (OpenCV -y)
    behind = cam.center - 7.0 * cam.R[2]
    to_gl = lambda p: (V @ np.append(p, 1.0))[:3]  # noqa: E731
    np.testing.assert_allclose(to_gl(ahead), [0.0, 0.0, -7.0], atol=1e-12)
    np.testing.assert_allclose(to_gl(above), [0.0, 2.0, -7.0], atol=1e-12)  # OpenGL's y is up
    assert to_gl(behind)[2] > 0.0


def test_gl_projection_lands_on_the_contracts_pixels():
    # The OpenGL clip -> window mapping with the contract's pixel centres must give what
    # project_points gives, for any K (off-centre principal point, fx != fy).
    cam = _camera()
    znear, zfar = 0.25, 3000.0
    VP = cam.gl_projection(znear, zfar) @ cam.gl_view()
    world = (np.array([[0.5, -0.7, 12.0], [-2.0, 1.0, 30.0], [0.0, 0.0, 1.0]]) - cam.t) @ cam.R
    clip = np.c_[world, np.ones(len(world))] @ VP.T
    ndc = clip[:, :3] / clip[:, 3:]
    # window: x_w = (x_ndc + 1) W / 2 measured from the left edge, rows from the bottom in GL
    u = (ndc[:, 0] + 1) * W / 2 - 0.5
    v = (1 - ndc[:, 1]) * H / 2 - 0.5
    uv, _ = cam.project(world)
    np.testing.assert_allclose(np.c_[u, v], uv, atol=1e-9)
    # depth: the near plane maps to -1, the far plane to +1
    for z, want in ((znear, -1.0), (zfar, 1.0)):
        c = cam.gl_projection(znear, zfar) @ np.array([0.0, 0.0, -z, 1.0])
        assert c[2] / c[3] == pytest.approx(want)


def test_camera_is_frozen_and_checked():
    K = intrinsics_from_fov(math.radians(60), 160, 120)
    R = rot_z(0.3)
    t = np.array([[1.0], [2.0], [3.0]])  # a column is accepted, stored as (3,)
    cam = Camera(K, R, t, 160, 120)
    assert cam.t.shape == (3,) and cam.K.dtype == np.float64
    K[0, 0] = 1.0  # the caller's arrays are copied
    assert cam.K[0, 0] != 1.0
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0
    with pytest.raises(AttributeError):
        cam.width = 10  # type: ignore[misc]
    with pytest.raises(ValueError):
        Camera(K, R[:2], t, 160, 120)
    with pytest.raises(ValueError):
        Camera(K, R, t, 0, 120)
    # from_fov is the same K as intrinsics_from_fov, the pose kept
    c2 = Camera.from_fov(math.radians(60), R, t, 160, 120)
    np.testing.assert_array_equal(c2.K, intrinsics_from_fov(math.radians(60), 160, 120))
    assert c2.K[0, 0] == pytest.approx(80 / math.tan(math.radians(30)))


def test_look_at_puts_the_target_on_the_optical_axis_with_the_world_up_on_screen_up():
    from omnigen.camera import look_at

    R, t = look_at((10.0, -20.0, 15.0), (1.0, 2.0, 0.0))
    assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    target_cam = R @ np.array([1.0, 2.0, 0.0]) + t
    assert np.allclose(target_cam[:2], 0.0, atol=1e-9) and target_cam[2] > 0
    above = R @ np.array([1.0, 2.0, 5.0]) + t  # a point above the target is higher in the image: -y
    assert above[1] < 0
    with pytest.raises(ValueError, match="parallel"):
        look_at((0.0, 0.0, 10.0), (0.0, 0.0, 0.0))


def test_a_camera_refuses_what_no_camera_is_and_stays_frozen_when_copied():
    import copy
    import pickle

    from omnigen.camera import Camera, intrinsics_from_fov, look_at

    K = intrinsics_from_fov(math.radians(60), 160, 120)
    R, t = look_at((0.0, -10.0, 5.0), (0.0, 0.0, 0.0))
    cam = Camera(K, R, t, 160.0, 120)  # a whole float is a size
    assert (cam.width, cam.height) == (160, 120)
    for bad, match in (((K, R, t, 160.9, 120), "width"), ((K, R, t, 160, 0), "height"),
                       ((K, R * 1.1, t, 160, 120), "not a rotation"), ((K, -R, t, 160, 120), "not a rotation"),
                       ((K, R, t + np.nan, 160, 120), "t: not finite")):
        with pytest.raises(ValueError, match=match):
            Camera(*bad)
    for copied in (pickle.loads(pickle.dumps(cam)), copy.deepcopy(cam), copy.copy(cam)):
        assert np.array_equal(copied.K, cam.K) and np.array_equal(copied.t, cam.t) and copied.width == 160
        assert not (copied.K.flags.writeable or copied.R.flags.writeable or copied.t.flags.writeable)
    with pytest.raises(ValueError, match="eye is at the target"):
        look_at((1.0, 2.0, 3.0), (1.0, 2.0, 3.0))


def test_a_drawn_cameras_position_is_frozen_with_the_rest():
    import pickle

    from omnigen.rigs.sampling import DrawnCamera

    K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])
    cam = DrawnCamera(K, np.eye(3), np.zeros(3), 160, 120, position=[1.0, 2.0, 3.0], yaw=0.1, pitch=0.2, hfov=1.0,
                      anchor="road")
    assert cam.camera_height == 3.0 and not cam.position.flags.writeable
    with pytest.raises(ValueError):
        cam.position[2] = 99.0
    again = pickle.loads(pickle.dumps(cam))
    assert isinstance(again, DrawnCamera) and again.anchor == "road" and not again.position.flags.writeable
