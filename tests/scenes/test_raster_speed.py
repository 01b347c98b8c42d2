"""The raster preview's speed-ups change no output: exact replicas of what they replaced.

- `seeding.choice_index` draws the same numbers as Generator.choice (so frames are unchanged);
- `annotate.mask_boxes` gives the counts and boxes np.unique / np.nonzero gave;
- `parts.wheel` gives the vertices `cylinder_between` gave;
- culling agents outside the view or behind the static city changes no pixel of the instance
  image or the depth.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnigen.rigs.annotate import mask_box, mask_boxes
from omnigen.scenes.assets.parts import cylinder_between, wheel
from omnigen.scenes.seeding import choice_index


def test_choice_index_draws_like_generator_choice():
    a, b = np.random.default_rng(11), np.random.default_rng(11)
    for _ in range(3000):
        n = int(a.integers(1, 10))
        b.integers(1, 10)
        p = a.random(n) ** 2 + 1e-6
        b.random(n)
        p = p / p.sum()
        assert int(a.choice(n, p=p)) == choice_index(b, p)
        assert int(a.choice(n, p=p)) == choice_index(b, p.tolist())
    assert a.random() == b.random()


def test_mask_boxes_match_unique_and_nonzero():
    rng = np.random.default_rng(2)
    for _ in range(10):
        inst = np.zeros((61, 83), np.uint16)
        for _ in range(int(rng.integers(0, 25))):
            y, x = int(rng.integers(0, 61)), int(rng.integers(0, 83))
            inst[y:y + int(rng.integers(1, 20)), x:x + int(rng.integers(1, 20))] = int(rng.integers(1, 65535))
        counts, boxes = mask_boxes(inst)
        ids, n = np.unique(inst, return_counts=True)
        assert {int(i): int(c) for i, c in zip(ids, n)} == {i: int(c) for i, c in enumerate(counts) if c}
        assert set(boxes) == set(ids.tolist()) - {0}
        for i in boxes:
            ys, xs = np.nonzero(inst == i)
            assert np.array_equal(boxes[i], mask_box(ys, xs))


def test_wheel_is_the_cylinder_it_replaced():
    for center, r, w in (((0.3, -0.8, 0.31), 0.31, 0.22), ((-2.0, 1.1, 0.5), 0.5, 0.3)):
        c = np.asarray(center)
        ref = cylinder_between(c - [0, w / 2, 0], c + [0, w / 2, 0], r, 16)
        got = wheel(center, r, w)
        assert np.array_equal(ref.faces, got.faces)
        assert np.allclose(ref.vertices, got.vertices, atol=1e-12)


def test_culling_changes_no_pixel(monkeypatch):
    # Skipped only for the external dependencies (here, not at module level, where it would skip
    # the pure-numpy tests above too); omnigen.scenes.raster_backend itself must import.
    pytest.importorskip("pyrender", reason="pyrender not installed")
    pytest.importorskip("OpenGL", reason="PyOpenGL not installed")
    from omnigen.camera import Camera, intrinsics_from_fov
    from omnigen.scenes import raster_backend as raster
    from omnigen.scenes.generate import SceneGenerator

    scene = SceneGenerator("tiny", 8).frame(8, 1)
    W, H = 160, 120
    K = intrinsics_from_fov(math.radians(75), W, H)
    eye, target = np.array([-30.0, -35.0, 45.0]), np.array([0.0, 0.0, 0.0])
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    t = -R @ eye
    try:
        rs = raster.RasterScene(scene)
    except Exception as exc:
        pytest.skip(f"headless EGL rendering unavailable: {exc}")
    try:
        culled = rs.render(Camera(K, R, t, W, H))
        kept = raster.visible_agents(scene.agents, Camera(K, R, t, W, H))
        assert len(kept) < len(scene.agents)  # the view misses some agents: culling did something
        monkeypatch.setattr(raster, "visible_agents", lambda agents, *a: list(range(len(agents))))
        monkeypatch.setattr(raster, "unoccluded_agents", lambda agents, chosen, *a: chosen)
        rs.update(scene)
        rs._agents_key = None
        full = rs.render(Camera(K, R, t, W, H))
    finally:
        rs.close()
    assert np.array_equal(culled.instance, full.instance)
    assert np.array_equal(culled.depth, full.depth)
    assert len(set(np.unique(full.instance)) - {0}) >= 3


def test_drawing_ranges_keeps_no_array_type_per_range_count(noon_raster):
    """PyOpenGL keeps a handler for every ctypes array type it is given, and (c_void_p * n) is a
    type of its own for each n: offsets made per draw grew resident memory by every range count a
    long run met (issue 48). The mesh's one offsets array adds none."""
    import gc

    from omnigen.camera import Camera, intrinsics_from_fov, look_at

    _, scene, rs = noon_raster
    camera = Camera(intrinsics_from_fov(math.radians(70), 96, 96), *look_at((0.0, -45.0, 35.0), (0.0, 0.0, 0.0)), 96, 96)
    rs.render(camera)
    assert rs.gl.color_builds >= 2  # a colour shader build per surface group drawn (the agents one of them)
    seen = sorted(rs._ranges)
    assert len(seen) >= 5

    def handlers() -> int:
        return sum(type(o).__name__ == "CtypesArrayHandler" for o in gc.get_objects())

    before = handlers()
    for n in range(1, len(seen) + 1):
        silhouettes = rs.render_instances(camera, seen[:n])
        assert set(np.unique(silhouettes)) - {0} <= set(seen[:n])
    assert handlers() - before <= 1
