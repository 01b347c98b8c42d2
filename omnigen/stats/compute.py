"""The numbers of the statistics report, computed over a dataset's columns at once.

Why columns: a report over 40,000 frames and 300,000 objects must take seconds, so nothing here
loops over objects in Python. Per-object quantities (distance, pixel height, image and ground
positions, prior z-scores) are derived once for the whole dataset (`Derived`); every section
(overall, each source, each view) is then the same set of reductions over a boolean mask.

Every number the page shows and every number a plot draws is in the returned dict, which is
written as stats.json: the plots and the page are pure functions of it. Histogram edges are
chosen once from the whole dataset and shared by every section, so sections compare bar for bar;
the ground-plane heatmap is the exception (an aerial camera sees hundreds of metres, a car's a
few tens), so each section picks its own extent.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from omnigen.conventions import CORNER_NAMES, FINE_CLASSES, NUM_KEYPOINTS, SOURCES, VIEWS
from omnigen.dataset import Dataset
from omnigen.priors import FAR_SIGMA, PRIORS, dims_z_scores

STATS_FORMAT = "omnigen-stats"
STATS_VERSION = 1

OCCLUSION_LEVEL_NAMES = ("fully visible", "partly", "largely", "unknown")
SUMMARY_KEYS = ("n", "mean", "std", "min", "p5", "p25", "median", "p75", "p95", "max")
IMAGE_HEATMAP_RANGE = (-0.25, 1.25)
"""Object centres are placed in image-normalised coordinates (x / W, y / H) so that images of
every size share one heatmap; the margin shows centres projected just outside the image."""
HEATMAP_BINS = 32
HIST_BINS = 30


# ---------------------------------------------------------------------------------------------
# Small reductions
# ---------------------------------------------------------------------------------------------


def rnd(x: float | None, digits: int = 6) -> float | None:
    """A float rounded to `digits` significant digits (None for NaN): short, stable JSON."""
    if x is None:
        return None
    x = float(x)
    if not math.isfinite(x):
        return None
    return float(f"{x:.{digits}g}")


def summary(values: np.ndarray) -> dict[str, float | int | None]:
    """Count, mean, spread and quantiles of the finite values (None where there are none)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return {k: (0 if k == "n" else None) for k in SUMMARY_KEYS}
    q = np.percentile(v, [5, 25, 50, 75, 95])
    return {"n": int(len(v)), "mean": rnd(v.mean()), "std": rnd(v.std()), "min": rnd(v.min()),
            "p5": rnd(q[0]), "p25": rnd(q[1]), "median": rnd(q[2]), "p75": rnd(q[3]), "p95": rnd(q[4]),
            "max": rnd(v.max())}


def histogram(values: np.ndarray, edges: list[float]) -> dict[str, Any]:
    """Counts of the finite values in the bins; values outside the edges are counted apart."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    counts, _ = np.histogram(v, bins=np.asarray(edges))
    return {"edges": edges, "counts": counts.tolist(), "outside": int(len(v) - counts.sum())}


def histogram2d(x: np.ndarray, y: np.ndarray, x_edges: list[float], y_edges: list[float]) -> dict[str, Any]:
    """2D counts (rows = y bins, columns = x bins, as an image is drawn) of the finite points."""
    ok = np.isfinite(x) & np.isfinite(y)
    counts, _, _ = np.histogram2d(y[ok], x[ok], bins=[np.asarray(y_edges), np.asarray(x_edges)])
    counts = counts.astype(np.int64)
    return {"x_edges": x_edges, "y_edges": y_edges, "counts": counts.tolist(),
            "outside": int(ok.sum() - counts.sum()), "missing": int((~ok).sum())}


def nice_ceil(x: float) -> float:
    """The smallest of 1, 2, 2.5, 5 times a power of ten that is >= x (axis limits people read)."""
    if not math.isfinite(x) or x <= 0:
        return 1.0
    p = 10.0 ** math.floor(math.log10(x))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * p >= x * (1 - 1e-12):
            return m * p
    return 10.0 * p


def linear_edges(values: np.ndarray, bins: int = HIST_BINS, lo: float | None = None, hi: float | None = None,
                 q: float = 100.0) -> list[float]:
    """Evenly spaced edges over the data (or the given limits); a constant column gets a unit span."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if lo is None:
        lo = float(v.min()) if len(v) else 0.0
    if hi is None:
        hi = float(np.percentile(v, q)) if len(v) else 1.0
    if hi - lo < 1e-9:
        lo, hi = lo - 0.5, hi + 0.5
    return [rnd(e) for e in np.linspace(lo, hi, bins + 1)]


def log_edges(hi: float, bins: int = HIST_BINS, lo: float = 1.0) -> list[float]:
    return [rnd(e) for e in np.geomspace(lo, max(hi, lo * 10), bins + 1)]


def fractions(counts: np.ndarray, total: int) -> list[float | None]:
    return [rnd(c / total, 4) if total else None for c in np.asarray(counts).tolist()]


# ---------------------------------------------------------------------------------------------
# Per-object and per-frame quantities, derived once
# ---------------------------------------------------------------------------------------------


@dataclass
class Derived:
    """Whole-dataset columns the sections reduce; built once by `derive`."""

    frame_source: np.ndarray  # (F,) object array of source names
    frame_view: np.ndarray
    n_objects: np.ndarray  # (F,) objects per frame
    ignore_regions: np.ndarray  # (F,) ignore regions per frame
    image_size: np.ndarray  # (F,) "WxH" strings
    camera: dict[str, np.ndarray]  # (F,) height_m, pitch_deg, focal_px, hfov_deg, vfov_deg
    has_plane: np.ndarray  # (F,) bool
    synthetic: np.ndarray  # (F,) bool: the frame has a synthetic block
    conditions: dict[str, dict[str, np.ndarray]]  # "weather"/"lighting" -> key -> (F,) values
    obj_frame: np.ndarray  # (N,)
    category: np.ndarray
    distance: np.ndarray  # metres from the camera centre to the cuboid centre
    box_w: np.ndarray  # 2D box width and height in pixels
    box_h: np.ndarray
    dims: np.ndarray  # (N, 3)
    dims_z: np.ndarray  # (N, 3) spreads from the class prior
    truncation: np.ndarray
    occlusion: np.ndarray
    occlusion_level: np.ndarray
    in_image: np.ndarray  # (N, 8)
    occluded: np.ndarray
    behind: np.ndarray
    image_xy: np.ndarray  # (N, 2) projected centre / (W, H); NaN when the centre is behind the camera
    ground_xy: np.ndarray  # (N, 2) (right, forward) metres on the ground plane; NaN without a plane


def derive(ds: Dataset) -> Derived:
    t, o = ds.table, ds.objects
    n_frames = len(t)
    frame = o.frame.astype(np.int64)
    fx, fy = t.K[:, 0, 0], t.K[:, 1, 1]
    width, height = t.width.astype(np.float64), t.height.astype(np.float64)
    camera = {
        "height_m": t.camera_height.astype(np.float64),
        "pitch_deg": np.degrees(t.camera_pitch.astype(np.float64)),
        "focal_px": fx.astype(np.float64),
        "hfov_deg": np.degrees(2 * np.arctan(width / (2 * fx))),
        "vfov_deg": np.degrees(2 * np.arctan(height / (2 * fy))),
    }
    extras = t.extras
    ignore = np.fromiter((len(e.get("ignore_regions") or ()) for e in extras), dtype=np.int64, count=n_frames)
    synthetic = np.fromiter((e.get("synthetic") is not None for e in extras), dtype=bool, count=n_frames)
    conditions = {part: _condition_columns([(e.get("synthetic") or {}).get(part) for e in extras])
                  for part in ("weather", "lighting")}
    sizes = np.char.add(np.char.add(t.width.astype(str), "x"), t.height.astype(str)).astype(object)

    # Projected cuboid centre, normalised by the image size.
    proj = np.einsum("nij,nj->ni", t.K[frame], o.center)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = proj[:, :2] / proj[:, 2:3]
    uv[o.center[:, 2] <= 0] = np.nan
    image_xy = uv / np.stack([width[frame], height[frame]], axis=1)

    return Derived(
        frame_source=np.asarray(t.source, dtype=object), frame_view=np.asarray(t.view, dtype=object),
        n_objects=np.diff(ds.offsets).astype(np.int64), ignore_regions=ignore, image_size=sizes,
        camera=camera, has_plane=np.isfinite(t.ground_plane).all(axis=1), synthetic=synthetic,
        conditions=conditions, obj_frame=frame, category=o.category.astype(np.int64),
        distance=np.linalg.norm(o.center, axis=1), box_w=o.bbox[:, 2] - o.bbox[:, 0],
        box_h=o.bbox[:, 3] - o.bbox[:, 1], dims=o.dims, dims_z=dims_z_scores(o.category, o.dims),
        truncation=o.truncation, occlusion=o.occlusion, occlusion_level=o.occlusion_level.astype(np.int64),
        in_image=o.in_image, occluded=o.occluded, behind=o.behind_camera, image_xy=image_xy,
        ground_xy=ground_coordinates(t.ground_plane, frame, o.center, o.rotation, o.dims),
    )


def ground_frames(planes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame, the ground frame under the camera: origin (camera's foot), right and forward axes.

    Forward is the optical axis laid flat on the plane, so a BEV drawn in these axes has the
    camera at the bottom looking up; a camera looking straight down uses the image's up instead.
    All three are NaN for frames without a ground plane.
    """
    n, d = planes[:, :3], planes[:, 3]
    origin = -d[:, None] * n
    z = np.array([0.0, 0.0, 1.0])
    forward = z - n[:, 2:3] * n
    norm = np.linalg.norm(forward, axis=1)
    steep = ~(norm > 1e-6)
    if steep.any():  # nadir camera: the image's up (-y) laid on the plane
        up_img = np.array([0.0, -1.0, 0.0])
        forward[steep] = up_img - (n[steep] @ up_img)[:, None] * n[steep]
        norm = np.linalg.norm(forward, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        forward = forward / norm[:, None]
    right = np.cross(forward, n)
    return origin, right, forward


def ground_coordinates(planes: np.ndarray, frame: np.ndarray, center: np.ndarray, rotation: np.ndarray,
                       dims: np.ndarray) -> np.ndarray:
    """(N, 2) (right, forward) position in metres of each object's bottom centre on its frame's ground."""
    origin, right, forward = ground_frames(planes)
    bottom = center - rotation[:, :, 2] * (dims[:, 2:3] / 2)
    rel = bottom - origin[frame]
    return np.stack([(rel * right[frame]).sum(axis=1), (rel * forward[frame]).sum(axis=1)], axis=1)


def _condition_columns(blocks: list[dict[str, Any] | None]) -> dict[str, np.ndarray]:
    """Flatten per-frame weather (or lighting) dicts into one column per dotted key.

    Numbers become float columns (NaN where absent); strings and booleans object columns
    (None where absent). The renderer decides the keys; the report follows whatever it wrote.
    """
    flat: list[dict[str, Any]] = [_flatten(b) if isinstance(b, dict) else {} for b in blocks]
    keys = sorted({k for f in flat for k in f})
    cols: dict[str, np.ndarray] = {}
    for k in keys:
        values = [f.get(k) for f in flat]
        numeric = all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in values)
        if numeric:
            cols[k] = np.array([np.nan if v is None else float(v) for v in values], dtype=np.float64)
        else:
            cols[k] = np.array([None if v is None else str(v) for v in values], dtype=object)
    return cols


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        elif not isinstance(v, list):
            out[f"{prefix}{k}"] = v
    return out


# ---------------------------------------------------------------------------------------------
# Bins shared by every section
# ---------------------------------------------------------------------------------------------


def shared_bins(d: Derived) -> dict[str, Any]:
    """Histogram edges from the whole dataset, so every section's plots share their axes."""
    max_h = float(np.nanmax(d.box_h)) if len(d.box_h) else 100.0
    dist = d.distance[np.isfinite(d.distance)]
    bins: dict[str, Any] = {
        "distance_m": linear_edges(dist, lo=0.0, hi=nice_ceil(np.percentile(dist, 99.5)) if len(dist) else 100.0),
        "pixel_height": log_edges(nice_ceil(max(max_h, 10.0))),
        "truncation": [rnd(e) for e in np.linspace(0, 1, 11)],
        "occlusion": [rnd(e) for e in np.linspace(0, 1, 11)],
        "image_x": [rnd(e) for e in np.linspace(*IMAGE_HEATMAP_RANGE, HEATMAP_BINS + 1)],
        "image_y": [rnd(e) for e in np.linspace(*IMAGE_HEATMAP_RANGE, HEATMAP_BINS + 1)],
        "camera": {k: linear_edges(v) for k, v in d.camera.items()},
        "conditions": {part: {k: linear_edges(v, bins=12) for k, v in cols.items() if v.dtype != object}
                       for part, cols in d.conditions.items()},
    }
    return bins


def ground_extent(xy: np.ndarray) -> tuple[list[float], list[float]]:
    """Heatmap edges for one section: forward from 0 to the 99th percentile, lateral symmetric."""
    ok = np.isfinite(xy).all(axis=1)
    if not ok.any():
        return ([rnd(e) for e in np.linspace(-10, 10, HEATMAP_BINS + 1)],
                [rnd(e) for e in np.linspace(0, 20, HEATMAP_BINS + 1)])
    fwd = nice_ceil(float(np.percentile(np.maximum(xy[ok, 1], 0), 99)))
    lat = nice_ceil(float(np.percentile(np.abs(xy[ok, 0]), 99)))
    lat = max(lat, fwd / 4)  # keep the picture readable when everything sits on one line
    return ([rnd(e) for e in np.linspace(-lat, lat, HEATMAP_BINS + 1)],
            [rnd(e) for e in np.linspace(min(0.0, -fwd / 20), fwd, HEATMAP_BINS + 1)])


# ---------------------------------------------------------------------------------------------
# One section
# ---------------------------------------------------------------------------------------------


def section(d: Derived, fmask: np.ndarray, bins: dict[str, Any], title: str) -> dict[str, Any]:
    """Every number of one section (a subset of frames and their objects)."""
    omask = fmask[d.obj_frame]
    n_frames, n_obj = int(fmask.sum()), int(omask.sum())
    cat = d.category[omask]
    class_counts = np.bincount(cat, minlength=len(FINE_CLASSES))
    per_class = {c: cat == i for i, c in enumerate(FINE_CLASSES) if class_counts[i]}
    dist, bh = d.distance[omask], d.box_h[omask]
    npf = d.n_objects[fmask]

    out: dict[str, Any] = {
        "title": title,
        "frames": n_frames,
        "objects": n_obj,
        "ignore_regions": int(d.ignore_regions[fmask].sum()),
        "classes": {c: int(class_counts[i]) for i, c in enumerate(FINE_CLASSES)},
        "class_fractions": dict(zip(FINE_CLASSES, fractions(class_counts, n_obj))),
        # frames holding at least one object of the class: how often a class shows up, the
        # frequency a scene preset's [agents] sets (objects alone hide 30 cones in one frame)
        "class_frames": dict(zip(FINE_CLASSES, _frames_per_class(d.obj_frame[omask], cat).tolist())),
        "image_sizes": dict(Counter(d.image_size[fmask].tolist()).most_common(8)),
        "objects_per_frame": {"summary": summary(npf), "counts": np.bincount(npf).tolist() if n_frames else []},
        "distance_m": {**histogram(dist, bins["distance_m"]), "summary": summary(dist),
                       "by_class": {c: summary(dist[m]) for c, m in per_class.items()}},
        "pixel_height": {**histogram(bh, bins["pixel_height"]), "summary": summary(bh),
                         "width_summary": summary(d.box_w[omask]),
                         "by_class": {c: summary(bh[m]) for c, m in per_class.items()}},
        "dims": _dims(d, omask, per_class),
        "occlusion": _occlusion(d, omask, bins),
        "corners": _corners(d, omask),
        "camera": _camera(d, fmask, bins),
        "heatmaps": _heatmaps(d, omask, bins),
        "conditions": _conditions(d, fmask, bins),
    }
    return out


def _frames_per_class(frame: np.ndarray, cat: np.ndarray) -> np.ndarray:
    """Per fine class, the number of distinct frames among `frame` whose objects include it."""
    k = len(FINE_CLASSES)
    pairs = np.unique(frame.astype(np.int64) * k + cat)
    return np.bincount(pairs % k, minlength=k)


def _dims(d: Derived, omask: np.ndarray, per_class: dict[str, np.ndarray]) -> dict[str, Any]:
    dims, z = d.dims[omask], d.dims_z[omask]
    far = (np.abs(z) > FAR_SIGMA).any(axis=1)
    out = {}
    for c, m in per_class.items():
        out[c] = {"n": int(m.sum()), "far_outside_prior": int(far[m].sum()),
                  **{axis: summary(dims[m, j]) for j, axis in enumerate("lwh")}}
    return out


def _occlusion(d: Derived, omask: np.ndarray, bins: dict[str, Any]) -> dict[str, Any]:
    n = int(omask.sum())
    levels = np.bincount(d.occlusion_level[omask], minlength=4)[:4]
    trunc, occ = d.truncation[omask], d.occlusion[omask]
    truncated = int((trunc > 0).sum())
    return {
        "levels": dict(zip(OCCLUSION_LEVEL_NAMES, levels.tolist())),
        "level_fractions": dict(zip(OCCLUSION_LEVEL_NAMES, fractions(levels, n))),
        "fraction": {**histogram(occ, bins["occlusion"]), "summary": summary(occ)},
        "truncation": {**histogram(trunc, bins["truncation"]), "summary": summary(trunc),
                       "truncated": truncated, "truncated_fraction": rnd(truncated / n, 4) if n else None},
    }


def _corners(d: Derived, omask: np.ndarray) -> dict[str, Any]:
    """Per corner (0-7): how often it is in the image, occluded there, visible, behind the camera."""
    n = int(omask.sum())
    ii, oc, be = d.in_image[omask], d.occluded[omask], d.behind[omask]
    counts = {"in_image": ii.sum(axis=0), "occluded_in_image": (ii & oc).sum(axis=0),
              "visible": (ii & ~oc).sum(axis=0), "behind_camera": be.sum(axis=0)}
    return {"names": list(CORNER_NAMES), "objects": n,
            "counts": {k: v.astype(int).tolist() for k, v in counts.items()},
            "fractions": {k: fractions(v, n) for k, v in counts.items()},
            "in_image_per_object": np.bincount(ii.sum(axis=1), minlength=NUM_KEYPOINTS + 1).tolist()}


def _camera(d: Derived, fmask: np.ndarray, bins: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {k: {**histogram(v[fmask], bins["camera"][k]), "summary": summary(v[fmask])}
                           for k, v in d.camera.items()}
    out["without_ground_plane"] = int((~d.has_plane[fmask]).sum())
    return out


def _heatmaps(d: Derived, omask: np.ndarray, bins: dict[str, Any]) -> dict[str, Any]:
    ixy, gxy = d.image_xy[omask], d.ground_xy[omask]
    gx_edges, gy_edges = ground_extent(gxy)
    return {"image": histogram2d(ixy[:, 0], ixy[:, 1], bins["image_x"], bins["image_y"]),
            "ground": histogram2d(gxy[:, 0], gxy[:, 1], gx_edges, gy_edges)}


def _conditions(d: Derived, fmask: np.ndarray, bins: dict[str, Any]) -> dict[str, Any]:
    """The weather and lighting mix of the rendered frames in the section."""
    rendered = fmask & d.synthetic
    out: dict[str, Any] = {"frames": int(rendered.sum())}
    for part, cols in d.conditions.items():
        block = {}
        for key, col in cols.items():
            v = col[rendered]
            if col.dtype == object:
                counts = Counter(x for x in v.tolist() if x is not None)
                block[key] = {"kind": "categorical", "counts": dict(sorted(counts.items()))}
            else:
                block[key] = {"kind": "numeric", **histogram(v, bins["conditions"][part][key]), "summary": summary(v)}
        out[part] = block
    return out


# ---------------------------------------------------------------------------------------------
# The whole dataset
# ---------------------------------------------------------------------------------------------


def compute_stats(ds: Dataset, derived: Derived | None = None) -> dict[str, Any]:
    """stats.json without its health and gallery parts: dataset facts, priors, bins, sections."""
    d = derived if derived is not None else derive(ds)
    bins = shared_bins(d)
    everything = np.ones(len(ds), dtype=bool)
    sources = [s for s in SOURCES if (d.frame_source == s).any()] + sorted(set(d.frame_source) - set(SOURCES))
    views = [v for v in VIEWS if (d.frame_view == v).any()] + sorted(set(d.frame_view) - set(VIEWS))
    return {
        "format": STATS_FORMAT,
        "version": STATS_VERSION,
        "dataset": {"path": str(ds.root), "name": ds.manifest.get("name", ds.root.name),
                    "frames": len(ds), "objects": len(ds.objects)},
        "classes": list(FINE_CLASSES),
        "priors": {"far_sigma": FAR_SIGMA,
                   "classes": {c: {"mean": list(PRIORS[c].mean), "std": list(PRIORS[c].std)} for c in FINE_CLASSES}},
        "bins": bins,
        "overall": section(d, everything, bins, "All frames"),
        "by_source": {s: section(d, d.frame_source == s, bins, f"Source: {s}") for s in sources},
        "by_view": {v: section(d, d.frame_view == v, bins, f"View: {v}") for v in views},
    }
