"""What traffic leaves on a road, as a map over the city that both backends read for asphalt.

A real road is not one grey. Vehicles drip oil, coolant and brake dust between their wheels, so
each driving lane has a darker band along its middle, darkest over the last tens of metres before
a stop line, where vehicles stand with their engines running (the dark smudges on junction
approaches in any aerial photograph); tyres lay rubber along the two wheel paths of each lane; the
gutter along a kerb collects grit, leaves and standing water. After a snowfall traffic clears the
wheel paths down to wet asphalt long before the rest of the road: dark tracks through white.

Made once per city from its lanes, stop lines, roads and junctions (pure geometry: the same map on
every machine and every run, no random draw), on a WEAR_CELL grid; the raster shader (gl_raster
surface(), asphalt only) and Cycles (blender_backend's surface material, an image) read two channels:
- r, stain: the lane-middle band (a Gaussian across the lane, OIL_SD) at OIL_BASE of full strength
  along the lane, rising to full over the QUEUE_REACH metres before a stop line (decaying
  upstream, as the queue thins), and the gutter (GUTTER_WIDTH from each kerb, not across junctions);
- g, wheel tracks: two Gaussians (TRACK_SD) at +-TRACK_HALF from each driving lane's middle (half
  a car's track width), and at least JUNCTION_CHURN over a junction's box, where turning
  vehicles cross every part of it (in snow: churned slush, not a grid of tracks).
How dark each makes the asphalt, and how much snow the tracks clear: WEAR_* below, which the raster
shader (gl_raster) and Cycles' surface material (blender_backend) apply alike.
"""

from __future__ import annotations

import math

import numpy as np

WEAR_CELL = 0.2  # m: a wheel track (about 0.5 m wide) spans a few cells
MAX_SIDE_CELLS = 4096  # the map's longest side; a larger city gets coarser cells
OIL_SD = 0.3  # m: drips fall on a band about a metre wide between the wheels
OIL_BASE = 0.45  # the band's strength along a lane, of its strength where vehicles queue
QUEUE_REACH = 25.0  # m: the e-folding length of the queue's stain upstream of a stop line
TRACK_HALF = 0.8  # m: half a car's track width (1.5-1.6 m)
TRACK_SD = 0.18  # m: the spread of the wheel paths (tyre width and lateral wander)
GUTTER_WIDTH = 0.45  # m: the grimy band along each kerb
JUNCTION_CHURN = 0.6  # the wheel-track value all over a junction's box: turning traffic runs everywhere there
# What the map does to asphalt, at its full value (both backends: gl_raster's shader and Cycles'
# surface material): an oil-soaked queue zone before a stop line is about half as bright as the lane
# around it (the dark smudges of junction approaches), a lane's middle elsewhere about a fifth
# darker (OIL_BASE), the rubber of the wheel paths a little darker; in snow, wheels clear 90% of
# it off their tracks (the raster's snow patches). On albedo a: a (1 - STAIN s - RUBBER t + STAIN RUBBER s t).
WEAR_STAIN = 0.45
WEAR_RUBBER = 0.12
WEAR_CLEARED = 0.9


def _frame(shape: tuple[int, int], x0: float, y0: float, cell: float):
    ny, nx = shape
    return (x0 + (np.arange(nx) + 0.5) * cell, y0 + (np.arange(ny) + 0.5) * cell)


def _window(xs: np.ndarray, ys: np.ndarray, lo, hi):
    """Index slices of the cells whose centres lie in the box [lo, hi] (x, y)."""
    i0, i1 = np.searchsorted(xs, lo[0]), np.searchsorted(xs, hi[0], side="right")
    j0, j1 = np.searchsorted(ys, lo[1]), np.searchsorted(ys, hi[1], side="right")
    return slice(j0, j1), slice(i0, i1)


def _local(xs, ys, sl, origin, heading: float):
    """Along and across coordinates (m) of the cells in `sl` in the frame at `origin` turned by `heading`."""
    X, Y = np.meshgrid(xs[sl[1]] - origin[0], ys[sl[0]] - origin[1])
    c, s = math.cos(heading), math.sin(heading)
    return X * c + Y * s, -X * s + Y * c


def road_wear_map(city, cell: float = WEAR_CELL) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The stain (r) and wheel-track (g) map of `city`'s roads, (ny, nx, 2) uint8 (row j at
    y = y0 + (j + 0.5) cell), and (x0, y0, 1 / width, 1 / height) in metres for the shader's lookup.
    Outside the roads both are 0; the shader applies them to asphalt only."""
    xmin, ymin, xmax, ymax = city.bounds
    cell = max(cell, (max(xmax - xmin, ymax - ymin) + 2.0) / MAX_SIDE_CELLS)
    x0, y0 = xmin - cell, ymin - cell
    nx, ny = int(math.ceil((xmax - xmin) / cell)) + 2, int(math.ceil((ymax - ymin) / cell)) + 2
    xs, ys = _frame((ny, nx), x0, y0, cell)
    stain = np.zeros((ny, nx), dtype=np.float32)
    tracks = np.zeros((ny, nx), dtype=np.float32)
    queue = np.zeros((ny, nx), dtype=np.float32)
    # where vehicles wait: upstream of each stop line, across its width (the approach's lanes)
    for m in city.markings:
        if m.kind != "stop_line":
            continue
        reach = 4.0 * QUEUE_REACH
        half = m.width / 2.0
        h = (math.cos(m.yaw), math.sin(m.yaw))
        ends = [(m.center[0] + a * h[0] - b * h[1], m.center[1] + a * h[1] + b * h[0]) for a in (-reach, 0.0) for b in (-half, half)]
        sl = _window(xs, ys, np.min(ends, axis=0), np.max(ends, axis=0))
        u, v = _local(xs, ys, sl, m.center, m.yaw)
        w = np.where((u <= 0.0) & (u >= -reach) & (np.abs(v) <= half), np.exp(u / QUEUE_REACH), 0.0)
        queue[sl] = np.maximum(queue[sl], w)
    # lanes: the oil band along the middle and the two wheel tracks
    for road in city.roads:
        for lane in road.lanes:
            if lane.kind != "driving":
                continue
            pad = TRACK_HALF + 4.0 * TRACK_SD
            lo = np.minimum(lane.start, lane.end) - pad
            hi = np.maximum(lane.start, lane.end) + pad
            sl = _window(xs, ys, lo, hi)
            u, v = _local(xs, ys, sl, lane.start, lane.heading)
            inside = (u >= 0.0) & (u <= lane.length) & (np.abs(v) <= lane.width / 2.0)
            oil = np.exp(-0.5 * (v / OIL_SD) ** 2) * (OIL_BASE + (1.0 - OIL_BASE) * queue[sl])
            wheels = np.exp(-0.5 * ((np.abs(v) - TRACK_HALF) / TRACK_SD) ** 2)
            stain[sl] = np.maximum(stain[sl], np.where(inside, oil, 0.0))
            tracks[sl] = np.maximum(tracks[sl], np.where(inside, wheels, 0.0))
    # junctions: turning traffic wears (and, in snow, churns) the whole box
    boxes = [(i.center, i.size) for i in city.intersections]
    for c, size in boxes:
        half = np.asarray(size, dtype=np.float64) / 2.0
        sl = _window(xs, ys, np.asarray(c) - half, np.asarray(c) + half)
        tracks[sl] = np.maximum(tracks[sl], JUNCTION_CHURN)
    # gutters: along each kerb, except where the road opens into a junction
    for road in city.roads:
        heading = math.atan2(road.end[1] - road.start[1], road.end[0] - road.start[0])
        length = math.hypot(road.end[0] - road.start[0], road.end[1] - road.start[1])
        pad = road.width / 2.0 + 0.5
        sl = _window(xs, ys, np.minimum(road.start, road.end) - pad, np.maximum(road.start, road.end) + pad)
        u, v = _local(xs, ys, sl, road.start, heading)
        d = road.width / 2.0 - np.abs(v)  # distance in from the kerb
        g = np.where((u >= 0.0) & (u <= length) & (d >= 0.0), np.clip(1.0 - d / GUTTER_WIDTH, 0.0, 1.0) ** 2, 0.0)
        X, Y = np.meshgrid(xs[sl[1]], ys[sl[0]])
        for c, size in boxes:
            g[(np.abs(X - c[0]) < size[0] / 2.0) & (np.abs(Y - c[1]) < size[1] / 2.0)] = 0.0
        stain[sl] = np.maximum(stain[sl], 0.8 * g)
    out = np.stack([stain, tracks], axis=-1)
    out = np.round(255.0 * np.clip(out, 0.0, 1.0)).astype(np.uint8)
    return out, (float(x0), float(y0), float(1.0 / (nx * cell)), float(1.0 / (ny * cell)))
