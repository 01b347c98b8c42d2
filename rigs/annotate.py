"""Annotations of a rendered frame: the contract's object records from depth, instance mask and scene.

Rules (docs/rendering.md repeats them):
- The cuboid: each agent's world cuboid (centre, dims, yaw about +z) moved into the camera frame
  with the rig's extrinsics (`Box3D.transformed(R, t)`); keypoints, in_image, behind_camera,
  bbox and truncation come from `ObjectRecord.from_box`, as for every other source.
- `occluded` per corner: a corner hidden by the cuboid itself (`self_occluded_corners`) stays
  occluded. A corner in front of the camera and in the image is also occluded when no pixel of
  the 3x3 block around it (pixel = the corner rounded to the nearest pixel centre) either shows
  the object itself (instance id) or has depth >= z_corner - tol, tol = DEPTH_TOL_ABS +
  DEPTH_TOL_REL * z_corner (5 cm + 1%): something else is in front of it. The 3x3 block absorbs
  the half pixel between the corner and the pixel centre that samples it. Corners outside the
  image or behind the camera keep the self-occlusion flag only (nothing in the image can tell).
- `bbox_visible`: the box of the object's mask pixels, in the contract's pixel convention
  (pixel centres at integers, so a pixel spans +-0.5): [xmin - 0.5, ymin - 0.5, xmax + 0.5, ymax + 0.5].
- `occlusion` = 1 - visible mask pixels / silhouette pixels, the silhouette being the object drawn
  alone at the same camera (BlenderProc's BOP writer, Unity Perception). Method: the agents that
  have visible pixels are split greedily into groups whose projected-cuboid boxes (grown by 2 px)
  do not overlap; each group is drawn alone in one instance pass (nothing else in the scene), and
  since every mesh lies inside its cuboid, each object's pixels in its group's pass are exactly its
  silhouette alone. Cost: one instance-only pass per group (typically 2 to 6 per frame) instead of
  one per object. `occlusion_level` from `conventions.occlusion_level_from_fraction`.
- `track_id` = the agent's instance id (in a sequence the same agent keeps it at every instant);
  `velocity` = the agent's world velocity in m/s where the Scene has one (a sequence's instants).
- Left out: objects with fewer than MIN_VISIBLE_PIXELS visible mask pixels (this includes objects
  entirely hidden, and cuboids whose projection reaches the image but whose mesh shows nowhere).
  Objects with 1 to MIN_VISIBLE_PIXELS - 1 visible pixels are kept as `ignore_regions` (their
  visible box, label "small-<class>") so a detector is not punished for finding them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from omnigen.camera import Camera
from omnigen.conventions import occlusion_level_from_fraction
from omnigen.geometry import self_occluded_corners
from omnigen.record import IgnoreRegion, ObjectRecord
from omnigen.rigs.sampling import agent_box
from omnigen.scenes.description import Scene

MIN_VISIBLE_PIXELS = 16
DEPTH_TOL_ABS = 0.05
DEPTH_TOL_REL = 0.01
GROUP_MARGIN_PX = 2.0

SilhouetteFn = Callable[[list[int]], np.ndarray]


@dataclass
class Annotation:
    objects: list[ObjectRecord]
    ignore_regions: list[IgnoreRegion]
    silhouette_passes: int


def mask_box(ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """The box of mask pixels in the contract's convention (pixel centres at integers)."""
    return np.array([xs.min() - 0.5, ys.min() - 0.5, xs.max() + 0.5, ys.max() + 0.5], dtype=np.float64)


def mask_boxes(instance: np.ndarray) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Pixel count per id (index = id) and the mask box (`mask_box`) of every id other than 0.

    One pass over the image instead of one comparison per object: the non-background pixels are
    sorted by id (a radix sort for 16-bit ids) and each id's run reduced to its extremes.
    """
    flat = instance.ravel()
    counts = np.bincount(flat, minlength=1)
    nz = np.flatnonzero(flat)
    if not len(nz):
        return counts, {}
    order = np.argsort(flat[nz], kind="stable")
    pix = nz[order]
    ids = flat[pix]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    W = instance.shape[1]
    ys, xs = pix // W, pix % W
    x0, x1 = np.minimum.reduceat(xs, starts), np.maximum.reduceat(xs, starts)
    y0, y1 = np.minimum.reduceat(ys, starts), np.maximum.reduceat(ys, starts)
    boxes = {int(i): np.array([a - 0.5, b - 0.5, c + 0.5, d + 0.5], dtype=np.float64)
             for i, a, b, c, d in zip(ids[starts].tolist(), x0.tolist(), y0.tolist(), x1.tolist(), y1.tolist())}
    return counts, boxes


def corner_occlusion(rec: ObjectRecord, depth: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """Self-occlusion, plus occlusion by others for corners in the image (see the module doc)."""
    occ = self_occluded_corners(rec.box)
    H, W = depth.shape
    z = rec.box.corners()[:, 2]
    for j in range(8):
        if occ[j] or not rec.in_image[j] or rec.behind_camera[j]:
            continue
        u, v = int(np.floor(rec.keypoints[j, 0] + 0.5)), int(np.floor(rec.keypoints[j, 1] + 0.5))
        u0, u1, v0, v1 = max(u - 1, 0), min(u + 2, W), max(v - 1, 0), min(v + 2, H)
        d = depth[v0:v1, u0:u1]
        ids = instance[v0:v1, u0:u1]
        tol = DEPTH_TOL_ABS + DEPTH_TOL_REL * z[j]
        seen = (ids == rec.instance_id) | (d >= z[j] - tol)
        occ[j] = not bool(seen.any())
    return occ


def _groups(boxes: dict[int, np.ndarray]) -> list[list[int]]:
    """Greedy colouring: ids whose boxes (grown by GROUP_MARGIN_PX) do not overlap share a group."""
    m = np.array([-GROUP_MARGIN_PX, -GROUP_MARGIN_PX, GROUP_MARGIN_PX, GROUP_MARGIN_PX])
    groups: list[list[int]] = []
    grown: list[list[np.ndarray]] = []
    for iid in sorted(boxes, key=lambda i: (-(boxes[i][2] - boxes[i][0]) * (boxes[i][3] - boxes[i][1]), i)):
        b = boxes[iid] + m
        for g, gb in zip(groups, grown):
            arr = np.asarray(gb)
            if not ((arr[:, 0] < b[2]) & (b[0] < arr[:, 2]) & (arr[:, 1] < b[3]) & (b[1] < arr[:, 3])).any():
                g.append(iid)
                gb.append(b)
                break
        else:
            groups.append([iid])
            grown.append([b])
    return groups


def annotate(scene: Scene, cam: Camera, depth: np.ndarray, instance: np.ndarray, silhouettes: SilhouetteFn) -> Annotation:
    """Object records (sorted by instance id) and ignore regions of one rendered frame."""
    W, H = cam.width, cam.height
    counts, boxes = mask_boxes(instance)
    visible_count = {i: c for i, c in enumerate(counts.tolist()) if c}
    candidates: dict[int, ObjectRecord] = {}
    ignore: list[IgnoreRegion] = []
    # Velocities are parallel to the agents in a sequence's Scene (world frame), absent otherwise.
    velocities = scene.velocities or (None,) * len(scene.agents)
    for a, velocity in zip(scene.agents, velocities):
        n = visible_count.get(a.instance_id, 0)
        if n == 0:
            continue
        rec = ObjectRecord.from_box(a.category, a.instance_id, agent_box(a, cam), cam.K, W, H)
        vis_box = boxes[a.instance_id]
        if rec is None or n < MIN_VISIBLE_PIXELS:
            ignore.append(IgnoreRegion(vis_box, f"small-{a.category}"))
            continue
        rec.bbox_visible = vis_box
        rec.track_id = a.instance_id  # the agent's id is its track: stable across a sequence's instants
        rec.velocity = None if velocity is None else np.asarray(velocity, dtype=np.float64)
        candidates[a.instance_id] = rec
    groups = _groups({i: r.bbox for i, r in candidates.items()})
    alone: dict[int, int] = {}
    for g in groups:
        img = silhouettes(g)
        gc = np.bincount(img.ravel(), minlength=max(g) + 1)
        alone.update({i: int(gc[i]) for i in g})
    objects = []
    for iid in sorted(candidates):
        rec = candidates[iid]
        full = max(alone.get(iid, 0), visible_count[iid])  # a pass can only lose pixels to rounding
        rec.occlusion = float(np.clip(1.0 - visible_count[iid] / full, 0.0, 1.0))
        rec.occlusion_level = occlusion_level_from_fraction(rec.occlusion)
        rec.occluded = corner_occlusion(rec, depth, instance)
        objects.append(rec)
    ignore.sort(key=lambda r: tuple(r.bbox))
    return Annotation(objects, ignore, len(groups))
