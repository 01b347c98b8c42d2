"""Synthetic BEV frames with known ground truth, and the similarity-aligned accuracy measures.

Shared by tests/detector/test_bev.py and benchmarks/bench_bev.py: a pitched pinhole camera above a flat
ground, boxes with known footprints projected exactly by omnigen.geometry, and the Umeyama
alignment that compares a BEV (known only up to a similarity) with the true ground coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omnigen.camera import intrinsics_from_fov
from omnigen.geometry import Box3D, project_points, rot_x, rot_z

W, H = 1280, 720


@dataclass
class SyntheticFrame:
    """Bottom corners of boxes on the ground: true (right, forward) metres and their exact pixels."""

    K: np.ndarray
    world: np.ndarray  # (N, 4, 2) footprint corners 4-7, ground (right, forward) metres
    pixels: np.ndarray  # (N, 4, 2) exact projections
    boxes_xywh: np.ndarray  # (N, 4) tight 2D boxes of the whole cuboids
    classes: list[str]


DIMS = {"car": (4.2, 1.8, 1.5), "truck": (8.0, 2.5, 3.2), "pedestrian": (0.6, 0.6, 1.75), "bus": (11.0, 2.6, 3.2)}


def synthetic_frame(rng: np.random.Generator, n: int = 6, same_heading: bool = False,
                    classes: tuple[str, ...] = ("car", "car", "car", "truck", "bus")) -> SyntheticFrame:
    """A camera 5-10 m up, pitched 15-35 deg down, hfov 60-90 deg; n boxes fully in view with random headings."""
    height = rng.uniform(5.0, 10.0)
    pitch = math.radians(rng.uniform(15, 35))
    K = intrinsics_from_fov(math.radians(rng.uniform(60, 90)), W, H)
    world_to_cam = rot_x(pitch) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    common = rng.uniform(-math.pi, math.pi)
    world, pixels, boxes, names = [], [], [], []
    tries = 0
    while len(world) < n and tries < 500:
        tries += 1
        cls = classes[int(rng.integers(len(classes)))]
        dims = np.array(DIMS[cls]) * rng.uniform(0.9, 1.1, 3)
        xy = np.array([rng.uniform(-15, 15), rng.uniform(8, 45)])
        yaw = common if same_heading else rng.uniform(-math.pi, math.pi)
        centre = world_to_cam @ np.array([xy[0], xy[1], -height + dims[2] / 2])
        box = Box3D(centre, dims, world_to_cam @ rot_z(yaw))
        uv, behind = project_points(K, box.corners())
        if behind.any() or not ((uv >= 0).all() and (uv[:, 0] < W).all() and (uv[:, 1] < H).all()):
            continue
        c, s = math.cos(yaw), math.sin(yaw)
        local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * dims[:2] / 2
        world.append(xy + local @ np.array([[c, s], [-s, c]]))
        pixels.append(uv[4:8])
        boxes.append([*uv.min(axis=0), *(uv.max(axis=0) - uv.min(axis=0))])
        names.append(cls)
    return SyntheticFrame(K, np.array(world), np.array(pixels), np.array(boxes), names)


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising ||dst - (s R src + t)||^2, proper rotation only (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    e = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    r = u @ e @ vt
    s = float(np.trace(np.diag(d) @ e) / (a ** 2).sum(axis=1).mean())
    return s, r, mu_d - s * r @ mu_s


def centre_error_pct(bev_fp: np.ndarray, world_fp: np.ndarray) -> float:
    """Largest centre error after the best similarity on all corners, in % of the scene's extent
    (the diagonal of the true footprints' bounding box)."""
    s, r, t = umeyama(bev_fp.reshape(-1, 2), world_fp.reshape(-1, 2))
    aligned = s * bev_fp.mean(axis=1) @ r.T + t
    pts = world_fp.reshape(-1, 2)
    extent = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    return 100.0 * float(np.linalg.norm(aligned - world_fp.mean(axis=1), axis=1).max()) / extent
