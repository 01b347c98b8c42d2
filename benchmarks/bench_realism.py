"""Realism benchmark: image statistics and object sizes of default raster frames against real frames.

Why: issue 26 found the raster frames easy to tell from real ones (flat, low contrast, brown haze
from above, narrow classes). This script measures that with numbers a change can move: it renders
(or reuses) default raster frames from each rig (ego, pole, drone) with `omnigen render --backend
raster --quality preview` and compares them with the real sample frames in ../shared/realdata:

- luminance Y = 0.299 R + 0.587 G + 0.114 B on the 8-bit sRGB values; per frame its mean and its
  standard deviation (the contrast figure of the issue: the median over frames);
- luminance and colour (R, G, B) histograms, 32 bins, averaged over frames (each frame weighs the
  same), compared with KITTI's by histogram intersection (1 = identical) and by the earth mover's
  distance in grey levels (0 = identical);
- colourfulness (Hasler and Suesstrunk 2003), per frame, median;
- edge density: the fraction of pixels whose Sobel gradient magnitude of Y (the 3x3 kernel divided
  by 8, so grey levels per pixel) is at least EDGE_THRESHOLD. Real frames are first resized (area
  resampling) to the renders' width, so that a pixel spans a similar angle in both;
- object sizes and distances: car length, pedestrian height and distance to the camera from the
  synthetic records, KITTI's labels (camera-0 rectified frame) and DAIR-V2X's label (distance from
  the virtual-LiDAR origin: the sample has no image and no calibration, and its LiDAR stands on the
  same pole as its camera).

The only real photographs here are KITTI's (ego view); there is no roadside or aerial image in
../shared/realdata, so pole and drone frames are compared with KITTI too, as the only reference for
what a real camera's histogram looks like. Without ../shared/realdata the comparisons are left out
with a one-line reason; the synthetic figures are still printed.

Cycles rows (issue 45): the same rigs rendered with `omnigen render --backend cycles` at its default
quality (--cycles-frames frames a rig at --cycles-size; 0 frames leaves them out), in the same
statistics and histograms, and the road's luminance beside KITTI's:

- the road's pixels in a render: those of no agent (instance 0) whose depth puts them on the
  record's ground plane (within ROAD_TOLERANCE): the road's top is the ground (z = 0), sidewalks
  and lots stand a kerb (0.15 m) higher, the ground beyond the city 0.05 m lower, and road
  markings (0.01 m up) lie on the road and count. No extra render pass: depth, instance mask and
  ground plane are in every rendered dataset. Per frame the median luminance of those pixels;
  per set the median over frames;
- KITTI's road: the sample has no road mask, so its ground ahead of the car stands in for it: the
  KITTI_ROAD_AHEAD metres ahead of camera 2, KITTI_ROAD_HALF_WIDTH either side, on the plane
  KITTI_CAMERA_HEIGHT below the camera (KITTI's camera height), labelled boxes left out; the 10th
  to 90th percentile of those pixels' luminance is the range a render's road median is set against.

It also prints issue 26's class figure: 10 frames (6 drone + 4 pole, 320x240, raster, the default
preset): how many classes appear (traffic cones among them?), the median car length and the range
of pedestrian heights. The last line is the contrast figure per rig against the issue's targets.

    .venv/bin/python benchmarks/bench_realism.py [--frames 12] [--size 640] [--work runs/realism]
        [--seed 0] [--scene NAME] [--realdata ../shared/realdata] [--out realism.json] [--no-classes]
        [--cycles-frames 4] [--cycles-size 320] [--cycles-rigs ego,pole,drone]
    .venv/bin/python benchmarks/bench_realism.py --figures [DIR]    # docs/realism.md's two figures (docs/images)

`--figures` draws, from the same renders, docs/realism.md's rendered frames beside the real ones
with their histograms (realism-ego.png, realism-pole.png) instead of printing the tables.

Renders are kept in --work and reused while the renderer's sources (scenes/, rigs/, omnigen/) are
unchanged; any change to them renders again (a stamp file holds their hash, a timing file the
render's wall time, so a reused Cycles render still reports its seconds per frame).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import math
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

RIGS = ("ego", "pole", "drone")
TARGETS = {"ego": 55.0, "pole": 55.0, "drone": 40.0}
"""Issue 26's contrast targets: median per-frame luminance std of default raster frames."""
BINS = 32
HIST_SPAN = 256.0
"""Histograms cover 8-bit values over [0, HIST_SPAN): 255 falls in the last bin."""
EDGE_THRESHOLD = 32.0
"""Grey levels per pixel (the Sobel response divided by 8) at which a pixel counts as an edge: a
step of 64 grey levels between neighbours passes, sensor noise and smooth shading do not."""
CLASS_FRAMES = {"drone": 6, "pole": 4}
CLASS_SIZE = (320, 240)
CAR_LENGTH_RANGE = (3.6, 4.9)
PED_HEIGHT_RANGE = (1.5, 1.95)
MIN_CLASSES = 6
SOURCE_DIRS = ("scenes", "rigs", "omnigen")
STAMP = "sources.sha256"
TIMING = "timing.json"
CYCLES_FRAMES, CYCLES_SIZE = 4, 320
ROAD_TOLERANCE = 0.03
"""Metres from the ground plane within which a render's background pixel counts as road (the road's
top is the plane; sidewalks stand 0.15 m above it, the ground beyond the city 0.05 m below)."""
KITTI_CAMERA_HEIGHT = 1.65
KITTI_ROAD_AHEAD = (5.0, 20.0)
KITTI_ROAD_HALF_WIDTH = 2.0
ROAD_PERCENTILES = (10.0, 90.0)


# ---------------------------------------------------------------------------------------------
# Image statistics (pure functions on uint8 RGB arrays; the tests call them on synthetic arrays)
# ---------------------------------------------------------------------------------------------


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Y = 0.299 R + 0.587 G + 0.114 B on the 8-bit values (float64, 0-255): the issue's definition."""
    rgb = np.asarray(rgb, dtype=np.float64)
    return rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114


def sobel_magnitude(y: np.ndarray) -> np.ndarray:
    """Gradient magnitude of a 2D array by the 3x3 Sobel kernels divided by 8 (grey levels per
    pixel; a step of s between two columns gives s/2 on both), edges replicated at the border."""
    p = np.pad(np.asarray(y, dtype=np.float64), 1, mode="edge")
    gx = (p[:-2, 2:] + 2 * p[1:-1, 2:] + p[2:, 2:] - p[:-2, :-2] - 2 * p[1:-1, :-2] - p[2:, :-2]) / 8.0
    gy = (p[2:, :-2] + 2 * p[2:, 1:-1] + p[2:, 2:] - p[:-2, :-2] - 2 * p[:-2, 1:-1] - p[:-2, 2:]) / 8.0
    return np.hypot(gx, gy)


def edge_density(rgb: np.ndarray, threshold: float = EDGE_THRESHOLD) -> float:
    """Fraction of pixels whose Sobel magnitude of luminance is at least `threshold`."""
    return float((sobel_magnitude(luminance(rgb)) >= threshold).mean())


def colourfulness(rgb: np.ndarray) -> float:
    """Hasler and Suesstrunk's colourfulness (2003): 0 for grey, about 30-60 for ordinary photos."""
    rgb = np.asarray(rgb, dtype=np.float64)
    rg = rgb[..., 0] - rgb[..., 1]
    yb = 0.5 * (rgb[..., 0] + rgb[..., 1]) - rgb[..., 2]
    return float(math.hypot(rg.std(), yb.std()) + 0.3 * math.hypot(rg.mean(), yb.mean()))


def histogram(values: np.ndarray, bins: int = BINS) -> np.ndarray:
    """Normalised histogram of 0-255 values in `bins` equal bins over [0, HIST_SPAN) (sums to 1)."""
    h, _ = np.histogram(np.asarray(values, dtype=np.float64).ravel(), bins=bins, range=(0.0, HIST_SPAN))
    return h / max(h.sum(), 1)


def bin_centres(bins: int = BINS) -> np.ndarray:
    """The 8-bit value at the middle of each of histogram()'s bins (where the figure plots them)."""
    return (np.arange(bins) + 0.5) * HIST_SPAN / bins


def intersection(p: np.ndarray, q: np.ndarray) -> float:
    """Histogram intersection of two normalised histograms: 1 identical, 0 disjoint."""
    return float(np.minimum(p, q).sum())


def emd(p: np.ndarray, q: np.ndarray, span: float = HIST_SPAN) -> float:
    """Earth mover's distance between two normalised 1D histograms over [0, span), in the values'
    units (grey levels): the L1 distance of their cumulative sums times the bin width."""
    return float(np.abs(np.cumsum(p) - np.cumsum(q)).sum() * span / len(p))


@dataclass
class FrameStats:
    """One image's figures."""

    lum_mean: float
    lum_std: float
    edge_density: float
    colourfulness: float
    hist_lum: np.ndarray
    hist_rgb: np.ndarray  # (3, BINS)


def frame_stats(rgb: np.ndarray) -> FrameStats:
    y = luminance(rgb)
    return FrameStats(float(y.mean()), float(y.std()), edge_density(rgb), colourfulness(rgb), histogram(y),
                      np.stack([histogram(rgb[..., c]) for c in range(3)]))


@dataclass
class SetStats:
    """A set of frames: medians over frames, and the frames' mean histograms."""

    name: str
    frames: int
    lum_mean: float
    lum_std: float
    lum_std_per_frame: list[float]  # unrounded (the figure picks its frame by them); to_dict rounds
    edge_density: float
    colourfulness: float
    hist_lum: np.ndarray
    hist_rgb: np.ndarray

    def to_dict(self) -> dict:
        d = asdict(self)
        d["lum_std_per_frame"] = [round(v, 3) for v in self.lum_std_per_frame]
        d["hist_lum"] = self.hist_lum.round(6).tolist()
        d["hist_rgb"] = self.hist_rgb.round(6).tolist()
        return d


def set_stats(name: str, images: list[np.ndarray]) -> SetStats:
    fs = [frame_stats(im) for im in images]
    if not fs:
        raise ValueError(f"{name}: no frames")
    med = lambda k: float(np.median([getattr(f, k) for f in fs]))  # noqa: E731
    return SetStats(name, len(fs), med("lum_mean"), med("lum_std"), [f.lum_std for f in fs],
                    med("edge_density"), med("colourfulness"), np.mean([f.hist_lum for f in fs], axis=0),
                    np.mean([f.hist_rgb for f in fs], axis=0))


def compare(a: SetStats, b: SetStats) -> dict[str, float]:
    """Histogram distances of `a` from `b`: luminance intersection and EMD, per-channel EMD."""
    out = {"lum_intersection": intersection(a.hist_lum, b.hist_lum), "lum_emd": emd(a.hist_lum, b.hist_lum)}
    for c, name in enumerate("rgb"):
        out[f"{name}_emd"] = emd(a.hist_rgb[c], b.hist_rgb[c])
    out["rgb_intersection"] = float(np.mean([intersection(a.hist_rgb[c], b.hist_rgb[c]) for c in range(3)]))
    return out


# ---------------------------------------------------------------------------------------------
# Objects: sizes and distances
# ---------------------------------------------------------------------------------------------


@dataclass
class Objects:
    """Per source: each object's fine class, [l, w, h] and distance to the camera (m)."""

    name: str
    category: list[str] = field(default_factory=list)
    dims: list[tuple[float, float, float]] = field(default_factory=list)
    distance: list[float] = field(default_factory=list)
    note: str = ""

    def add(self, category: str, dims, distance: float) -> None:
        self.category.append(category)
        self.dims.append(tuple(float(v) for v in dims))
        self.distance.append(float(distance))

    def values(self, measure: str) -> np.ndarray:
        """'car length', 'ped. height' (pedestrians) or 'distance' (every object)."""
        if measure == "distance":
            return np.asarray(self.distance, dtype=np.float64)
        cls, axis = {"car length": ("car", 0), "ped. height": ("pedestrian", 2)}[measure]
        return np.asarray([d[axis] for c, d in zip(self.category, self.dims) if c == cls], dtype=np.float64)


MEASURES = ("car length", "ped. height", "distance")


def summary(v: np.ndarray) -> dict[str, float | int | None]:
    """n, median, 10th and 90th percentile, min and max (None where there are no values)."""
    if len(v) == 0:
        return {"n": 0, "median": None, "p10": None, "p90": None, "min": None, "max": None}
    return {"n": int(len(v)), "median": float(np.median(v)), "p10": float(np.percentile(v, 10)),
            "p90": float(np.percentile(v, 90)), "min": float(v.min()), "max": float(v.max())}


def synthetic_objects(name: str, records: list[dict]) -> Objects:
    """Every annotated object of a rendered dataset's records (dataset_records; box centre in the
    camera frame)."""
    objs = Objects(name)
    for record in records:
        for o in record["objects"]:
            b = o["box3d"]
            objs.add(o["category"], b["dims"], np.linalg.norm(b["center"]))
    return objs


def kitti_objects(root: Path) -> Objects:
    """KITTI label_2 objects by fine class; [l, w, h] from KITTI's h w l; distance of the box centre
    (location is the bottom-face centre) from camera 0, which camera 2 sits 6 cm beside."""
    from omnigen.converters.kitti import parse_labels
    from omnigen.conventions import KITTI_CLASSES

    objs = Objects("kitti", note="labels in the camera-0 rectified frame")
    for p in sorted((root / "label_2").glob("*.txt")):
        for lab in parse_labels(p.read_text(), str(p)):
            cat = KITTI_CLASSES.get(lab.type)
            if cat is None:
                continue
            h, w, l = lab.hwl
            x, y, z = lab.location
            objs.add(cat, (l, w, h), math.sqrt(x * x + (y - h / 2) ** 2 + z * z))
    return objs


def dair_labels(root: Path) -> list:
    """Every known-class object of the DAIR-V2X label files under `root` (each *.json, sorted), read
    by the converter (omnigen.converters.dair.parse_label: case-insensitive classes, numbers that
    may be strings, the same checks), so that the DAIR-V2X format is read in one place. Each is a
    LabelObject in the virtual-LiDAR frame: box centre, [l, w, h], yaw about +z
    (omnigen.formats.dair's convention)."""
    from omnigen.converters.dair import parse_label, read_json

    return [o for p in dair_label_files(root) for o in parse_label(read_json(p), p).objects]


def dair_label_files(root: Path) -> list[Path]:
    """The DAIR-V2X label files dair_labels reads: every *.json under `root`, sorted."""
    return sorted(root.rglob("*.json"))


def dair_objects(labels: list) -> Objects:
    """DAIR-V2X label objects (dair_labels) by fine class; distance of the box centre from the
    virtual-LiDAR origin."""
    objs = Objects("dair-v2x", note="distance from the virtual-LiDAR origin (no calibration in the sample)")
    for o in labels:
        objs.add(o.category, o.lwh, math.sqrt(sum(float(v) ** 2 for v in o.center)))
    return objs


DAIR_IMAGE = (1920, 1080)
"""DAIR-V2X's infrastructure images (the sample has none: the size is the dataset's)."""


def untruncated(o) -> bool:
    """A DAIR-V2X label object whose truncated_state is 0 (1 and 2: cut by the image's side or
    bottom edge, its 2d_box clipped to the image)."""
    return str(o.attributes.get("truncated_state", "0")).strip() in ("0", "0.0")


def dair_camera(labels: list) -> dict | None:
    """The sample's roadside camera as its own labels (dair_labels) imply it: the pinhole camera
    (focal length, pitch, yaw, roll and position; principal point at the centre of a DAIR_IMAGE
    frame, no distortion) under which each untruncated labelled cuboid's projected corners span its
    labelled 2D box, by least squares. Why: the sample has no image and no calibration, yet how a
    real roadside camera looks at a junction (how far down, how wide) is what the pole rig draws.
    Truncated objects are left out: their 2D boxes are clipped to the image, which the unclipped
    projection does not model (with them the fit missed the known cameras of the converters' DAIR
    fixture, omnigen.converters.dair_fixture, by degrees and metres). None with fewer than four
    untruncated boxes (seven unknowns)."""
    objs = [o for o in labels if untruncated(o)]
    if len(objs) < 4:
        return None
    from scipy.optimize import least_squares  # here: only this figure needs it

    from omnigen.geometry import cuboid_corners, rots_z

    corners = cuboid_corners(np.array([o.center for o in objs], dtype=np.float64),
                             np.array([o.lwh for o in objs], dtype=np.float64), rots_z([o.yaw for o in objs]))
    boxes = np.array([[o.box2d[0], o.box2d[1], o.box2d[2], o.box2d[3]] for o in objs], dtype=np.float64)
    cx, cy = DAIR_IMAGE[0] / 2.0, DAIR_IMAGE[1] / 2.0

    def project(q: np.ndarray) -> np.ndarray:
        f, pitch, yaw, roll, x, y, z = q
        cp, sp, cw, sw = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
        ahead, down, right = np.array([cp * cw, cp * sw, -sp]), np.array([-sp * cw, -sp * sw, -cp]), np.array([sw, -cw, 0.0])
        cr, sr = math.cos(roll), math.sin(roll)
        right, down = cr * right + sr * down, -sr * right + cr * down
        rel = corners - np.array([x, y, z])
        depth = rel @ ahead
        u, v = cx + f * (rel @ right) / depth, cy + f * (rel @ down) / depth
        return np.stack([u.min(axis=1), v.min(axis=1), u.max(axis=1), v.max(axis=1)], axis=1)

    best = None
    for z0 in (0.0, 3.0, 6.0, 10.0):  # a few starts: the fit is not convex
        for p0 in (0.05, 0.2, 0.4):
            fit = least_squares(lambda q: (project(q) - boxes).ravel(), [1500.0, p0, 0.0, 0.0, 0.0, 0.0, z0])
            if best is None or fit.cost < best.cost:
                best = fit
    f, pitch, _, _, _, _, z = best.x
    ground = float(corners[:, :, 2].min(axis=1).mean())
    vfov = 2.0 * math.degrees(math.atan(cy / f))
    return {"boxes": len(objs), "rms_px": float(np.sqrt(np.mean((project(best.x) - boxes) ** 2))),
            "pitch_deg": math.degrees(pitch), "hfov_deg": 2.0 * math.degrees(math.atan(cx / f)), "vfov_deg": vfov,
            "height_m": float(z) - ground, "top_edge_deg": math.degrees(pitch) - vfov / 2.0}


def camera_line(cam: dict) -> str:
    from omnigen.rigs.rig import load_rig

    pole = load_rig("pole")
    return (f"DAIR-V2X sample's camera (fitted to its {cam['boxes']} labelled boxes, rms {cam['rms_px']:.1f} px in "
            f"{DAIR_IMAGE[0]}x{DAIR_IMAGE[1]}): pitch {cam['pitch_deg']:.1f} deg below the horizon, hfov "
            f"{cam['hfov_deg']:.1f} deg, {cam['height_m']:.1f} m above the cuboids' bottoms, its frame's top edge "
            f"{abs(cam['top_edge_deg']):.1f} deg {'below' if cam['top_edge_deg'] >= 0 else 'above'} the horizon; the pole rig draws pitch {pole.pitch[0]:g}-{pole.pitch[1]:g} "
            f"deg, hfov {pole.hfov[0]:g}-{pole.hfov[1]:g} deg, height {pole.height[0]:g}-{pole.height[1]:g} m")


# ---------------------------------------------------------------------------------------------
# Frames: rendering (reused while the sources are unchanged) and reading
# ---------------------------------------------------------------------------------------------


def sources_hash() -> str:
    """sha256 over the renderer's sources (scenes/, rigs/, omnigen/: *.py and *.toml): renders in
    the work folder are reused only while it is unchanged."""
    h = hashlib.sha256()
    for d in SOURCE_DIRS:
        for p in sorted((ROOT / d).rglob("*")):
            if p.suffix in (".py", ".toml") and "__pycache__" not in p.parts:
                h.update(str(p.relative_to(ROOT)).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def render(rig: str, out: Path, frames: int, width: int, height: int, seed: int, stamp: str,
           scene: str | None = None, backend: str = "raster") -> Path:
    """`omnigen render --backend raster --quality preview` (backend "cycles": `--backend cycles` at
    the command's default quality) of frames 0..frames-1 into `out`, unless `out` already holds them
    from the same sources (`scene` None: the command's default preset); the wall time goes to
    TIMING. Raises RuntimeError with the command's last lines when it fails (no headless EGL, no
    bpy)."""
    import time

    stamp_file = out / STAMP
    have = len(list((out / "records").glob("*.json"))) if (out / "records").is_dir() else 0
    if have == frames and stamp_file.exists() and stamp_file.read_text().strip() == stamp:
        return out
    if out.exists():
        shutil.rmtree(out)
    quality = ["--quality", "preview"] if backend == "raster" else []
    cmd = [sys.executable, "-m", "omnigen", "render", "--rig", rig, "--frames", str(frames), "--out", str(out),
           "--seed", str(seed), "--width", str(width), "--height", str(height), "--backend", backend,
           *quality] + (["--scene", scene] if scene else [])
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if res.returncode != 0:
        tail = "\n".join((res.stdout + res.stderr).strip().splitlines()[-5:])
        raise RuntimeError(f"{' '.join(cmd[1:])} failed ({res.returncode}):\n{tail}")
    (out / TIMING).write_text(json.dumps({"seconds": time.perf_counter() - t0, "frames": frames}) + "\n")
    stamp_file.write_text(stamp + "\n")
    return out


def seconds_per_frame(dataset: Path) -> float | None:
    """The render's wall time a frame (the process start and the scene's build included), from TIMING."""
    p = dataset / TIMING
    if not p.exists():
        return None
    t = json.loads(p.read_text())
    return float(t["seconds"]) / max(int(t["frames"]), 1)


def shown(path: Path) -> str:
    """A path as the repository-relative one where it lies inside the repository (for printing)."""
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def rig_dataset(work: Path, rig: str, frames: int, size: int, seed: int, stamp: str, scene: str | None,
                backend: str = "raster") -> Path:
    """The benchmark's square renders of one rig in the work folder (the figure script reads the same)."""
    tag = f"-{Path(scene).stem}" if scene else ""
    prefix = "" if backend == "raster" else f"{backend}-"
    return render(rig, work / f"{prefix}{rig}-{frames}-{size}-s{seed}{tag}", frames, size, size, seed, stamp, scene, backend)


def read_rgb(path: Path, width: int | None = None) -> np.ndarray:
    """An image as uint8 RGB; resized (area resampling) to `width` when given and different."""
    from PIL import Image

    with Image.open(path) as im:
        im = im.convert("RGB")
        if width and im.width != width:
            im = im.resize((width, max(1, round(im.height * width / im.width))), Image.Resampling.BOX)
        return np.asarray(im)


def dataset_images(dataset: Path) -> list[np.ndarray]:
    return [read_rgb(p) for p in sorted((dataset / "images").glob("*.png"))]


def dataset_records(dataset: Path) -> list[dict]:
    """A rendered dataset's records (records/*.json, in frame order)."""
    return [json.loads(p.read_text()) for p in sorted((dataset / "records").glob("*.json"))]


def kitti_images(kitti: Path, width: int) -> list[np.ndarray]:
    """KITTI's left colour frames (image_2), resized to the renders' width as the benchmark measures them."""
    return [read_rgb(p, width) for p in sorted((kitti / "image_2").glob("*.png"))]


def dataset_scene(dataset: Path) -> str:
    return json.loads((dataset / "manifest.json").read_text())["render"]["scene"]


def real_sources(realdata: Path) -> tuple[Path | None, Path | None, list[str]]:
    """(KITTI training folder, DAIR-V2X label folder, notes on what is missing)."""
    notes = []
    kitti = realdata / "kitti" / "training"
    if not (kitti / "image_2").is_dir():
        notes.append(f"KITTI comparison skipped: no {kitti / 'image_2'}")
        kitti = None
    dair = realdata / "dair-v2x-c" / "infrastructure-side"
    if not (dair.is_dir() and any(dair.rglob("*.json"))):
        notes.append(f"DAIR-V2X comparison skipped: no label under {dair}")
        dair = None
    elif not any(p.suffix.lower() in (".jpg", ".png") for p in dair.rglob("*")):
        notes.append("DAIR-V2X: labels only (no image in the sample): its objects are compared, not its look")
    return kitti, dair, notes


# ---------------------------------------------------------------------------------------------
# The road's luminance (see the module doc)
# ---------------------------------------------------------------------------------------------


def _rays(K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel centre's ray (x / z, y / z) in the camera frame (x right, y down, z ahead)."""
    v, u = np.mgrid[0:height, 0:width]
    return (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]


def road_mask(depth: np.ndarray, instance: np.ndarray, K: np.ndarray, normal, offset: float,
              tolerance: float = ROAD_TOLERANCE) -> np.ndarray:
    """The pixels of a render that show road: no agent (instance 0), a finite depth (camera z), and
    a point within `tolerance` of the ground plane n . X + offset = 0 (the record's, camera frame)."""
    x, y = _rays(K, depth.shape[1], depth.shape[0])
    hit = np.isfinite(depth)
    z = np.where(hit, depth, 0.0)
    height = np.stack([x * z, y * z, z], axis=-1) @ np.asarray(normal, dtype=np.float64) + float(offset)
    return hit & (instance == 0) & (np.abs(height) < tolerance)


def road_medians(dataset: Path) -> list[float]:
    """Each frame's median luminance over its road pixels (road_mask), in frame order; a frame that
    shows no road is left out."""
    from omnigen.rigs.render import read_depth_exr, read_instance_png

    out = []
    for record in dataset_records(dataset):
        plane = record.get("ground_plane")
        if plane is None:
            continue
        syn = record["synthetic"]
        mask = road_mask(read_depth_exr(dataset / syn["depth"]), read_instance_png(dataset / syn["instance"]),
                         np.asarray(record["K"], dtype=np.float64), plane["normal"], plane["offset"])
        if mask.any():
            out.append(float(np.median(luminance(read_rgb(dataset / record["image"]))[mask])))
    return out


def ground_strip(K: np.ndarray, width: int, height: int, camera_height: float = KITTI_CAMERA_HEIGHT,
                 ahead: tuple[float, float] = KITTI_ROAD_AHEAD, half_width: float = KITTI_ROAD_HALF_WIDTH) -> np.ndarray:
    """The pixels of a level camera `camera_height` above flat ground whose ray meets the ground
    between `ahead` metres in front of it and within `half_width` of its axis: the lane ahead."""
    x, y = _rays(K, width, height)
    dist = np.where(y > 0, camera_height / np.where(y > 0, y, 1.0), np.inf)
    return (dist >= ahead[0]) & (dist <= ahead[1]) & (np.abs(x) * np.minimum(dist, ahead[1]) <= half_width)


def kitti_road_luminance(kitti: Path) -> np.ndarray:
    """The luminance of KITTI's ground ahead of the car (ground_strip through each frame's P2, every
    labelled box, DontCare too, left out), every frame's pixels together."""
    from omnigen.converters.kitti import parse_calib, parse_labels

    values = []
    for image in sorted((kitti / "image_2").glob("*.png")):
        calib, label = kitti / "calib" / f"{image.stem}.txt", kitti / "label_2" / f"{image.stem}.txt"
        if not calib.exists():
            continue
        rgb = read_rgb(image)
        mask = ground_strip(parse_calib(calib.read_text(), str(calib)).projection("P2")[:, :3], rgb.shape[1], rgb.shape[0])
        for lab in parse_labels(label.read_text(), str(label)) if label.exists() else []:
            x1, y1, x2, y2 = (int(round(c)) for c in lab.bbox)
            mask[max(y1, 0):max(y2 + 1, 0), max(x1, 0):max(x2 + 1, 0)] = False
        values.append(luminance(rgb)[mask])
    return np.concatenate(values) if values else np.zeros(0)


def road_summary(medians: list[float], span: tuple[float, float] | None) -> dict:
    """A set's road figure: its frames' road medians, their median, and how many lie in `span`."""
    inside = None if span is None else sum(span[0] <= m <= span[1] for m in medians)
    return {"frames": len(medians), "per_frame": [round(m, 1) for m in medians],
            "median": float(np.median(medians)) if medians else None, "in_range": inside,
            "in_span": None if span is None or not medians else bool(span[0] <= float(np.median(medians)) <= span[1])}


def road_rows(roads: dict[str, dict], span: tuple[float, float] | None, timing: dict[str, float | None]) -> list[list]:
    f = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
    return [[name, r["frames"], f(r["median"]), "-" if not r["per_frame"] else f"{min(r['per_frame']):.0f}-{max(r['per_frame']):.0f}",
             "-" if r["in_range"] is None else f"{r['in_range']}/{r['frames']}", f(timing.get(name))]
            for name, r in roads.items()]


# ---------------------------------------------------------------------------------------------
# The run
# ---------------------------------------------------------------------------------------------


def class_summary(mix, scenes: list[str]) -> dict:
    """Issue 26's class figure from the class mix of its 10 frames (omnigen.rigs.class_mix.ClassMix):
    the classes and their counts, whether cones are among them, the median car length, the
    pedestrian height range, and whether all of it meets the targets (>= 6 classes with cones,
    3.6-4.9 m, 1.5-1.95 m)."""
    counts = {c: mix.objects[c] for c in mix.classes}
    car_med = None if mix.median_car_length is None else float(mix.median_car_length)
    peds = mix.pedestrian_heights
    ped = (float(min(peds)), float(max(peds))) if peds else None
    ok = (len(counts) >= MIN_CLASSES and "traffic_cone" in counts and car_med is not None
          and CAR_LENGTH_RANGE[0] <= car_med <= CAR_LENGTH_RANGE[1] and ped is not None
          and PED_HEIGHT_RANGE[0] <= ped[0] and ped[1] <= PED_HEIGHT_RANGE[1])
    return {"frames": dict(CLASS_FRAMES), "size": list(CLASS_SIZE), "scene": scenes, "classes": counts,
            "n_classes": len(counts), "traffic_cone": "traffic_cone" in counts, "car_length_median": car_med,
            "pedestrian_height_range": ped, "meets_targets": ok}


def class_figure(work: Path, seed: int, stamp: str, scene: str | None) -> dict:
    """Issue 26's class figure on 6 drone + 4 pole frames at 320x240 (raster, default preset).

    The frames are this benchmark's own `omnigen render` runs (kept in the work folder and reused,
    like the rig renders); their records are counted by class_mix's ClassMix, the same counting
    as `class_counts(render=True)` applies to the renders it makes (and throws away) itself."""
    from omnigen.rigs.class_mix import ClassMix

    mix = ClassMix(how="raster render")
    scenes = set()
    for rig, n in CLASS_FRAMES.items():
        ds = render(rig, work / f"classes-{rig}-{n}-{CLASS_SIZE[0]}x{CLASS_SIZE[1]}-s{seed}", n, *CLASS_SIZE, seed,
                    stamp, scene)
        scenes.add(dataset_scene(ds))
        for record in dataset_records(ds):
            objs = record["objects"]
            mix.add_frame([o["category"] for o in objs], [tuple(o["box3d"]["dims"]) for o in objs])
    return class_summary(mix, sorted(scenes))


def class_line(cf: dict) -> str:
    """The class figure in one line, beside the issue's targets."""
    car = "-" if cf["car_length_median"] is None else f"{cf['car_length_median']:.2f}"
    ped = cf["pedestrian_height_range"]
    ped = "-" if ped is None else f"{ped[0]:.2f}-{ped[1]:.2f}"
    classes = ", ".join(f"{c} {n}" for c, n in cf["classes"].items())
    return (f"classes: {cf['n_classes']} in 10 frames (6 drone + 4 pole, 320x240, raster, scene "
            f"{', '.join(cf['scene'])}): {classes}; traffic cones {'yes' if cf['traffic_cone'] else 'no'} "
            f"(target >= {MIN_CLASSES} classes with cones); median car length {car} m (3.6-4.9); "
            f"pedestrian height {ped} m (1.5-1.95)")


def run(args: argparse.Namespace) -> dict:
    from omnigen.progress import print_table

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    stamp = sources_hash()
    kitti, dair, notes = real_sources(Path(args.realdata))
    datasets = {rig: rig_dataset(work, rig, args.frames, args.size, args.seed, stamp, args.scene) for rig in RIGS}
    cycles = {f"{rig} (cycles)": rig_dataset(work, rig, args.cycles_frames, args.cycles_size, args.seed, stamp, args.scene, "cycles")
              for rig in (args.cycles_rigs if args.cycles_frames > 0 else ())}
    scenes = sorted({dataset_scene(ds) for ds in (*datasets.values(), *cycles.values())})
    sets = {name: set_stats(name, dataset_images(ds)) for name, ds in (*datasets.items(), *cycles.items())}
    if kitti is not None:
        sets["kitti"] = set_stats("kitti", kitti_images(kitti, args.size))
    print(f"realism: {args.frames} frames a rig at {args.size}x{args.size}, raster preview, scene "
          f"{', '.join(scenes)}, seed {args.seed}; renders in {shown(work)}")
    if cycles:
        print(f"cycles rows: {args.cycles_frames} frames a rig at {args.cycles_size}x{args.cycles_size}, "
              f"omnigen render --backend cycles at its default quality")
    for n in notes:
        print(n)
    print_table("image statistics (median over frames)",
                ["set", "frames", "lum mean", "lum std", "edges", "colourful"],
                [[s.name, s.frames, f"{s.lum_mean:.1f}", f"{s.lum_std:.1f}", f"{s.edge_density:.3f}",
                  f"{s.colourfulness:.1f}"] for s in sets.values()])
    distances = {}
    if "kitti" in sets:
        distances = {name: compare(sets[name], sets["kitti"]) for name in (*RIGS, *cycles)}
        print_table("histograms against KITTI's (intersection: 1 same; EMD: grey levels, 0 same)",
                    ["rig", "lum inters.", "lum EMD", "RGB inters.", "R EMD", "G EMD", "B EMD"],
                    [[rig, f"{d['lum_intersection']:.3f}", f"{d['lum_emd']:.1f}", f"{d['rgb_intersection']:.3f}",
                      f"{d['r_emd']:.1f}", f"{d['g_emd']:.1f}", f"{d['b_emd']:.1f}"] for rig, d in distances.items()])

    roads, span = road_figure(datasets | cycles, kitti)
    where = "" if span is None else f", p10-p90 {span[0]:.1f}-{span[1]:.1f}"
    print_table("road luminance (each frame's median over its road pixels; KITTI: its ground "
                f"{KITTI_ROAD_AHEAD[0]:g}-{KITTI_ROAD_AHEAD[1]:g} m ahead, every pixel{where})",
                ["set", "frames", "road median", "per frame", "in KITTI's p10-p90", "s/frame"],
                road_rows(roads, span, {name: seconds_per_frame(ds) for name, ds in cycles.items()}))

    objects = [synthetic_objects(rig, dataset_records(ds)) for rig, ds in datasets.items()]
    if kitti is not None:
        objects.append(kitti_objects(kitti))
    labels = dair_labels(dair) if dair is not None else None
    if labels is not None:
        objects.append(dair_objects(labels))
    sizes = {o.name: {m: summary(o.values(m)) for m in MEASURES} for o in objects}
    camera = dair_camera(labels) if labels is not None else None
    f = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    print_table("object sizes and distances (m)", ["source", "measure", "n", "median", "p10", "p90", "min", "max"],
                [[name, m, s["n"], f(s["median"]), f(s["p10"]), f(s["p90"]), f(s["min"]), f(s["max"])]
                 for name, by in sizes.items() for m, s in by.items()])

    result = {"frames": args.frames, "size": args.size, "seed": args.seed, "scene": scenes, "notes": notes,
              "edge_threshold": EDGE_THRESHOLD, "bins": BINS, "images": {k: s.to_dict() for k, s in sets.items()},
              "histogram_distances_to_kitti": distances, "objects": sizes, "targets": TARGETS,
              "sources_sha256": stamp, "dair_camera": camera}
    if camera is not None:
        print(camera_line(camera))
    if not args.no_classes:
        cf = class_figure(work, args.seed, stamp, args.scene)
        result["class_figure"] = cf
        print(class_line(cf))
    result["road_luminance"] = {"kitti_p10_p90": span, "sets": roads,
                                "cycles_seconds_per_frame": {name: seconds_per_frame(ds) for name, ds in cycles.items()}}
    if cycles:
        print(road_line(roads, span, list(cycles)))
    result["lum_std"] = {rig: sets[rig].lum_std for rig in RIGS}
    result["meets_contrast_targets"] = all(sets[r].lum_std >= TARGETS[r] for r in RIGS)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print("realism: " + ", ".join(f"{rig} lum std {sets[rig].lum_std:.1f} (>= {TARGETS[rig]:.0f})" for rig in RIGS))
    return result


def road_figure(datasets: dict[str, Path], kitti: Path | None) -> tuple[dict[str, dict], tuple[float, float] | None]:
    """Each set's road_summary, KITTI's row (its pixels' median; frames: how many KITTI frames), and
    KITTI's road p10-p90 (None without the real sample)."""
    span, roads = None, {name: road_medians(ds) for name, ds in datasets.items()}
    if kitti is not None:
        k = kitti_road_luminance(kitti)
        if k.size:
            span = tuple(float(v) for v in np.percentile(k, ROAD_PERCENTILES))
            out = {name: road_summary(m, span) for name, m in roads.items()}
            out["kitti"] = {"frames": len(list((kitti / "image_2").glob("*.png"))), "per_frame": [], "median": float(np.median(k)),
                            "in_range": None, "in_span": None}
            return out, span
    return {name: road_summary(m, span) for name, m in roads.items()}, span


def road_line(roads: dict[str, dict], span: tuple[float, float] | None, names: list[str]) -> str:
    """The Cycles rows' road medians beside KITTI's range, in one line."""
    where = "no KITTI sample" if span is None else f"KITTI's road p10-p90 {span[0]:.1f}-{span[1]:.1f}"
    parts = []
    for name in names:
        r = roads[name]
        verdict = "" if r["in_span"] is None else (" in range" if r["in_span"] else " OUT of range")
        parts.append(f"{name} road median {'-' if r['median'] is None else format(r['median'], '.1f')}{verdict}")
    return f"realism: {', '.join(parts)} ({where})"


# ---------------------------------------------------------------------------------------------
# --figures: rendered frames beside the real ones, with their histograms (docs/realism.md)
# ---------------------------------------------------------------------------------------------
# Numbers alone do not show what a reader should look for; a rendered ego frame beside a real
# KITTI frame does. realism-ego.png: a rendered ego frame beside a KITTI frame (each the frame of its
# set whose luminance std is nearest the set's median, so neither is picked for looks), below them
# the luminance and R, G, B histograms of both sets (averaged over frames). realism-pole.png: a
# rendered pole frame beside the DAIR-V2X sample as far as it goes: the sample has a label and no
# image, so its objects are drawn from above (the virtual-LiDAR frame, x forward, y left) beside the
# pole frame's own objects (camera frame moved onto the ground plane); below, the pole frames'
# histograms against KITTI's (the only real photographs here) and the distances to the camera
# against DAIR-V2X's. Each PNG is written at DPI and reduced to 256 colours so that it stays well
# under 400 KB.

DPI = 80
CLASS_COLOURS = {"car": "tab:blue", "van": "tab:cyan", "truck": "tab:orange", "bus": "tab:red", "tram": "tab:brown",
                 "pedestrian": "tab:green", "cyclist": "tab:olive", "motorcyclist": "tab:purple",
                 "tricyclist": "tab:pink", "barrow": "tab:gray", "traffic_cone": "gold", "misc": "black"}


def representative(s: SetStats) -> int:
    """Index of the frame whose luminance std is nearest the set's median (as the benchmark measured
    them)."""
    return int(np.argmin(np.abs(np.asarray(s.lum_std_per_frame) - s.lum_std)))


def save_small(fig, path: Path) -> int:
    """Save a figure as a 256-colour PNG (photographs in it dither acceptably); returns its bytes."""
    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    buf.seek(0)
    with Image.open(buf) as im:
        small = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    path.parent.mkdir(parents=True, exist_ok=True)
    small.save(path, optimize=True)
    return path.stat().st_size


def plot_histograms(ax, sets: list[tuple[SetStats, str]], title: str) -> None:
    """Luminance (black) and R, G, B histograms of each set; the first set solid, the next dashed."""
    centres = bin_centres()
    for s, style in sets:
        ax.plot(centres, s.hist_lum, color="black", ls=style, lw=1.6, label=f"{s.name} luminance")
        for c, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
            ax.plot(centres, s.hist_rgb[c], color=colour, ls=style, lw=0.9)
    ax.set_xlim(0, 255)
    ax.set_xlabel("8-bit value (R, G, B in colour)")
    ax.set_ylabel("fraction of pixels")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)


def show_image(ax, im: np.ndarray, title: str) -> None:
    ax.imshow(im)
    ax.set_title(title, fontsize=9)
    ax.axis("off")


def ego_figure(ego: list[np.ndarray], kitti: list[np.ndarray] | None, k: SetStats | None, path: Path) -> int:
    """The ego figure; `k` is set_stats of the `kitti` frames (None without them)."""
    import matplotlib.pyplot as plt

    e = set_stats("rendered ego", ego)
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), gridspec_kw={"height_ratios": [1.3, 1]})
    i = representative(e)
    show_image(axes[0, 0], ego[i], f"rendered ego (raster), frame {i}: lum std {e.lum_std_per_frame[i]:.1f}")
    if kitti:
        j = representative(k)
        show_image(axes[0, 1], kitti[j], f"KITTI training frame {j}: lum std {k.lum_std_per_frame[j]:.1f}")
        plot_histograms(axes[1, 0], [(e, "-"), (k, "--")], "luminance and R, G, B: rendered (solid), KITTI (dashed)")
        d = compare(e, k)
        axes[1, 1].axis("off")
        rows = [("", "rendered ego", "KITTI"), ("frames", str(e.frames), str(k.frames)),
                ("median luminance std", f"{e.lum_std:.1f}", f"{k.lum_std:.1f}"),
                ("median luminance mean", f"{e.lum_mean:.1f}", f"{k.lum_mean:.1f}"),
                ("median edge density", f"{e.edge_density:.3f}", f"{k.edge_density:.3f}"),
                ("median colourfulness", f"{e.colourfulness:.1f}", f"{k.colourfulness:.1f}"),
                ("luminance hist. intersection", f"{d['lum_intersection']:.3f}", ""),
                ("luminance EMD (grey levels)", f"{d['lum_emd']:.1f}", "")]
        tab = axes[1, 1].table(cellText=[list(r) for r in rows], loc="center", cellLoc="left", colWidths=[0.56, 0.22, 0.22])
        tab.auto_set_font_size(False)
        tab.set_fontsize(8)
        tab.scale(1, 1.4)
    else:
        axes[0, 1].axis("off")
        axes[0, 1].text(0.5, 0.5, "no KITTI frames in ../shared/realdata", ha="center", va="center")
        plot_histograms(axes[1, 0], [(e, "-")], "luminance and R, G, B: rendered ego")
        axes[1, 1].axis("off")
    fig.tight_layout()
    size = save_small(fig, path)
    plt.close(fig)
    return size


def ground_view(record: dict) -> list[tuple[str, float, float, float, float, float]]:
    """A synthetic frame's objects from above: (class, forward, left, yaw, l, w) in metres, on the
    ground plane under the camera, forward along the camera's view projected onto the ground."""
    n = np.asarray(record["ground_plane"]["normal"], dtype=np.float64)  # the contract's: unit, pointing up
    n = n / np.linalg.norm(n)
    z = np.array([0.0, 0.0, 1.0])
    fwd = z - (z @ n) * n
    fwd /= np.linalg.norm(fwd)
    left = np.cross(n, fwd)
    out = []
    for o in record["objects"]:
        c = np.asarray(o["box3d"]["center"], dtype=np.float64)
        heading = np.asarray(o["box3d"]["rotation"], dtype=np.float64)[:, 0]
        l, w, _ = o["box3d"]["dims"]
        out.append((o["category"], float(c @ fwd), float(c @ left), math.atan2(heading @ left, heading @ fwd), l, w))
    return out


def dair_view(labels: list) -> list[tuple[str, float, float, float, float, float]]:
    """The DAIR-V2X label's objects (bench_realism.dair_labels: the converter's reading) from above
    in the virtual-LiDAR frame (x forward, y left; the yaw about +z, 0 along +x, as
    omnigen.formats.dair reads it)."""
    return [(o.category, float(o.center[0]), float(o.center[1]), o.yaw, float(o.lwh[0]), float(o.lwh[1]))
            for o in labels]


def draw_top(ax, objs, fill: bool, label: str) -> None:
    """Objects as rectangles from above (their cuboids' top corners 0-3, omnigen.geometry's):
    forward up the page, left to the left."""
    from matplotlib.patches import Polygon

    from omnigen.geometry import cuboid_corners, rot_z

    for cat, x, y, yaw, l, w in objs:
        corners = cuboid_corners(np.array([x, y, 0.0]), np.array([l, w, 0.0]), rot_z(yaw))[:4, :2]
        pts = [(-c[1], c[0]) for c in corners]  # page x = -left, page y = forward
        colour = CLASS_COLOURS.get(cat, "black")
        ax.add_patch(Polygon(pts, closed=True, fill=fill, facecolor=colour, edgecolor=colour, lw=1.0, alpha=0.8))
    ax.plot([], [], "s", mfc="gray" if fill else "none", mec="gray", ls="", label=label)


def pole_figure(pole: list[np.ndarray], records: list[dict], k: SetStats | None, labels: list | None,
                distances: np.ndarray, path: Path, label_names: tuple[str, ...] | list[str] = ()) -> int:
    """The pole figure; `k` is KITTI's set_stats, `labels` the DAIR-V2X sample's (dair_labels),
    read from the label files `label_names` (their stems, for the legend)."""
    import matplotlib.pyplot as plt

    p = set_stats("rendered pole", pole)
    fig, axes = plt.subplots(2, 2, figsize=(11, 8), gridspec_kw={"height_ratios": [1.2, 1]})
    i = representative(p)
    show_image(axes[0, 0], pole[i], f"rendered pole (raster), frame {i}: lum std {p.lum_std_per_frame[i]:.1f}")
    ax = axes[0, 1]
    ours, theirs = ground_view(records[i]), (dair_view(labels) if labels is not None else [])
    draw_top(ax, ours, fill=False, label=f"pole frame {i} (outline)")
    if labels is not None:
        names = ", ".join(label_names) or "sample"
        draw_top(ax, theirs, fill=True, label=f"DAIR-V2X-C {names} label{'s' if len(label_names) > 1 else ''} (filled)")
    ax.plot([0], [0], "k^", ms=8, label="camera / LiDAR")
    everything = ours + theirs
    reach = max([10.0] + [abs(o[1]) + o[4] for o in everything] + [2 * abs(o[2]) + o[4] for o in everything])
    ax.set_xlim(-0.8 * reach, reach / 2)  # room on the left for the legend
    ax.set_ylim(-5, reach)
    ax.set_aspect("equal")
    ax.set_xlabel("metres to the right")
    ax.set_ylabel("metres forward")
    seen = sorted({o[0] for o in everything})
    for cat in seen:
        ax.plot([], [], "s", color=CLASS_COLOURS.get(cat, "black"), ls="", label=cat)
    ax.legend(fontsize=6, loc="lower left")
    ax.set_title("objects from above: the pole frame and the DAIR-V2X label (it has no image)", fontsize=9)
    if k is not None:
        plot_histograms(axes[1, 0], [(p, "-"), (k, "--")],
                        "pole (solid) against KITTI (dashed; no roadside photo in the sample)")
    else:
        plot_histograms(axes[1, 0], [(p, "-")], "luminance and R, G, B: rendered pole")
    ax = axes[1, 1]
    bins = np.linspace(0, 200, 21)
    ax.hist(np.clip(distances, 0, 200), bins=bins, density=True, alpha=0.6, label=f"rendered pole ({len(distances)} objects)")
    if labels is not None:
        dd = dair_objects(labels).values("distance")
        ax.hist(np.clip(dd, 0, 200), bins=bins, density=True, histtype="step", lw=2, color="black",
                label=f"DAIR-V2X sample ({len(dd)} objects)")
    ax.set_xlabel("distance to the camera (m; DAIR: to the LiDAR)")
    ax.set_ylabel("density")
    ax.legend(fontsize=7)
    ax.set_title("distances", fontsize=9)
    fig.tight_layout()
    size = save_small(fig, path)
    plt.close(fig)
    return size


def draw_figures(args: argparse.Namespace) -> None:
    """--figures: docs/realism.md's two figures from the benchmark's renders (rendered first where
    they are missing or stale), written into args.figures."""
    import matplotlib

    matplotlib.use("Agg")
    work, out = Path(args.work), Path(args.figures)
    stamp = sources_hash()
    kitti_root, dair, notes = real_sources(Path(args.realdata))
    for n in notes:
        print(n)
    ds = {rig: rig_dataset(work, rig, args.frames, args.size, args.seed, stamp, args.scene) for rig in ("ego", "pole")}
    kitti = kitti_images(kitti_root, args.size) if kitti_root else None
    k = set_stats("KITTI", kitti) if kitti else None
    size = ego_figure(dataset_images(ds["ego"]), kitti, k, out / "realism-ego.png")
    print(f"wrote {out / 'realism-ego.png'} ({size / 1024:.0f} KB)")
    records = dataset_records(ds["pole"])
    labels = dair_labels(dair) if dair is not None else None
    names = [p.stem for p in dair_label_files(dair)] if dair is not None else []
    size = pole_figure(dataset_images(ds["pole"]), records, k, labels,
                       synthetic_objects("pole", records).values("distance"), out / "realism-pole.png", names)
    print(f"wrote {out / 'realism-pole.png'} ({size / 1024:.0f} KB)")


def add_render_arguments(ap: argparse.ArgumentParser) -> None:
    """The options that name the renders and the real sample: the tables and --figures read the
    same renders from the same work folder."""
    ap.add_argument("--frames", type=int, default=12, help="frames a rig")
    ap.add_argument("--size", type=int, default=640, help="square frame size of the rig renders")
    ap.add_argument("--work", default=str(ROOT / "runs" / "realism"), help="render folder, reused")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scene", default=None, help="city preset or TOML (default: omnigen render's default)")
    ap.add_argument("--realdata", default=str(ROOT.parent / "shared" / "realdata"))


def _rig_list(text: str) -> list[str]:
    """--cycles-rigs: a comma-separated list of RIGS."""
    rigs = [r.strip() for r in text.split(",") if r.strip()]
    unknown = [r for r in rigs if r not in RIGS]
    if not rigs or unknown:
        raise argparse.ArgumentTypeError(f"{text!r}: choose rigs from {', '.join(RIGS)}")
    return rigs


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_render_arguments(ap)
    ap.add_argument("--out", default="", help="write the figures as JSON here")
    ap.add_argument("--no-classes", action="store_true", help="leave out the 10-frame class figure")
    ap.add_argument("--figures", nargs="?", const=str(ROOT / "docs" / "images"), default=None, metavar="DIR",
                    help="instead of the tables, draw docs/realism.md's two figures into DIR (default docs/images)")
    from omnigen.options import integer

    ap.add_argument("--cycles-frames", type=integer(0, None), default=CYCLES_FRAMES,
                    help=f"Cycles frames a rig (default {CYCLES_FRAMES}; 0: no Cycles rows)")
    ap.add_argument("--cycles-size", type=integer(16, 4096), default=CYCLES_SIZE,
                    help=f"square size of the Cycles renders (default {CYCLES_SIZE})")
    ap.add_argument("--cycles-rigs", type=_rig_list, default=list(RIGS), help=f"rigs of the Cycles rows (default {','.join(RIGS)})")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        draw_figures(args) if args.figures else run(args)
    except RuntimeError as exc:
        print(f"bench_realism: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
