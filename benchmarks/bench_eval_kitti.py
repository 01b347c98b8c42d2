"""Speed of `omnigen eval-kitti` on KITTI val's size: 3,769 frames (target: under 30 s).

Writes generated ground truth (about 7 objects a frame: cars, vans, pedestrians, cyclists, trucks,
DontCare regions, with KITTI's spread of sizes, occlusion and truncation) and noisy predictions
(jittered boxes, misses, duplicates, false alarms, low-scored clutter) as KITTI label folders in a
temporary folder, then times `evaluate_folders` (reading both folders included) and prints the
median of --repeats runs and the AP table.

    .venv/bin/python benchmarks/bench_eval_kitti.py
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.detector.evaluation.kitti_eval import CLASSES, METRICS, evaluate_folders  # noqa: E402

# class, share of objects, (height, width, length) in metres
KINDS = [("Car", 0.55, (1.5, 1.6, 3.9)), ("Van", 0.06, (2.2, 1.9, 5.1)), ("Truck", 0.02, (3.2, 2.6, 10.0)),
         ("Pedestrian", 0.2, (1.76, 0.66, 0.84)), ("Person_sitting", 0.01, (1.27, 0.54, 0.8)),
         ("Cyclist", 0.06, (1.74, 0.6, 1.76)), ("DontCare", 0.10, None)]
FOCAL, CX, CY, WIDTH = 721.5, 609.6, 172.9, 1242


def _line(name, trunc, occ, box, dims, loc, ry, score=None) -> str:
    h, w, l = dims
    x, y, z = loc
    alpha = ry - math.atan2(x, z)
    s = (f"{name} {trunc:.2f} {occ} {alpha:.2f} {box[0]:.2f} {box[1]:.2f} {box[2]:.2f} {box[3]:.2f} "
         f"{h:.2f} {w:.2f} {l:.2f} {x:.2f} {y:.2f} {z:.2f} {ry:.2f}")
    return s if score is None else f"{s} {score:.4f}"


def _box2d(dims, loc) -> tuple[float, float, float, float]:
    """The 2D box of an upright cuboid seen by a KITTI-like camera (a bounding box of its corners)."""
    h, w, l = dims
    x, y, z = loc
    r = math.hypot(w, l) / 2
    zn = max(z - r, 1.0)
    return (FOCAL * (x - r) / zn + CX, FOCAL * (y - h) / zn + CY, FOCAL * (x + r) / zn + CX, FOCAL * y / zn + CY)


def write_frames(root: Path, n_frames: int, rng: np.random.Generator) -> tuple[Path, Path]:
    gt_dir, pred_dir = root / "label_2", root / "pred"
    gt_dir.mkdir(parents=True, exist_ok=True)
    pred_dir.mkdir(parents=True, exist_ok=True)
    shares = np.array([k[1] for k in KINDS])
    shares /= shares.sum()
    for f in range(n_frames):
        gt, pred = [], []
        for _ in range(int(rng.poisson(7))):
            name, _, dims = KINDS[rng.choice(len(KINDS), p=shares)]
            if dims is None:
                x1, y1 = rng.uniform(0, WIDTH - 60), rng.uniform(140, 200)
                gt.append(f"DontCare -1 -1 -10 {x1:.2f} {y1:.2f} {x1 + rng.uniform(10, 60):.2f} "
                          f"{y1 + rng.uniform(8, 30):.2f} -1 -1 -1 -1000 -1000 -1000 -10")
                continue
            dims = tuple(d * rng.uniform(0.9, 1.1) for d in dims)
            loc = (rng.uniform(-15, 15), rng.uniform(1.4, 1.9), rng.uniform(5, 70))
            ry = rng.uniform(-math.pi, math.pi)
            box = _box2d(dims, loc)
            trunc = float(np.clip(rng.exponential(0.08), 0, 0.9))
            occ = int(rng.choice(4, p=[0.55, 0.25, 0.15, 0.05]))
            gt.append(_line(name, trunc, occ, box, dims, loc, ry))
            if name not in CLASSES or rng.random() < 0.15:  # misses
                continue
            for _ in range(1 + int(rng.random() < 0.05)):  # an occasional duplicate
                dloc = tuple(np.array(loc) + rng.normal(0, [0.1, 0.05, 0.005 * loc[2] + 0.05]))
                ddims = tuple(np.array(dims) * rng.normal(1, 0.05, 3))
                dbox = tuple(np.array(box) + rng.normal(0, 3, 4))
                pred.append(_line(name, 0, 0, dbox, ddims, dloc, ry + rng.normal(0, 0.05), rng.beta(5, 2)))
        for _ in range(int(rng.poisson(3))):  # false alarms and low-scored clutter
            name, _, dims = KINDS[[0, 3, 5][rng.integers(3)]]
            loc = (rng.uniform(-15, 15), 1.6, rng.uniform(5, 70))
            pred.append(_line(name, 0, 0, _box2d(dims, loc), dims, loc, rng.uniform(-3, 3), rng.beta(1.5, 5)))
        (gt_dir / f"{f:06d}.txt").write_text("\n".join(gt) + "\n" if gt else "")
        if pred or rng.random() < 0.5:  # some frames without detections have no file at all
            (pred_dir / f"{f:06d}.txt").write_text("\n".join(pred) + "\n" if pred else "")
    return gt_dir, pred_dir


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3769)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="bench-eval-kitti-") as tmp:
        gt_dir, pred_dir = write_frames(Path(tmp), args.frames, np.random.default_rng(args.seed))
        n_gt = sum(len(p.read_text().splitlines()) for p in gt_dir.glob("*.txt"))
        n_pred = sum(len(p.read_text().splitlines()) for p in pred_dir.glob("*.txt"))
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            result = evaluate_folders(gt_dir, pred_dir)
            times.append(time.perf_counter() - t)

    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}")
    print(f"data: {args.frames} frames, {n_gt} ground-truth labels, {n_pred} detections")
    for kind in ("AP40", "AP11"):
        print(f"{kind} (easy / moderate / hard):")
        for cls in CLASSES:
            print("  " + "  ".join(f"{cls} {m}: " + "/".join(f"{v:5.1f}" for v in result[kind][cls][m])
                                   for m in METRICS))
    print(f"evaluate_folders: median {statistics.median(times):.2f} s over {args.repeats} runs "
          f"(min {min(times):.2f}, max {max(times):.2f}); target < 30 s")


if __name__ == "__main__":
    main()
