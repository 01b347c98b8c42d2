"""Accuracy and speed of the calibration-free BEV head on random synthetic frames (seeded).

Each frame: a camera 5-10 m up pitched 15-35 degrees down (hfov 60-90, 1280x720) and six boxes
(cars, trucks, buses) fully in view with random headings, 8-45 m ahead (tests/detector/test_bev.py's
`synthetic_frame`). Per frame the head sees the exact or noisy (Gaussian, sigma 2 px) corners 4-7.

- right-angle error: median over the frame's footprints of each one's largest |angle - 90 deg|,
  with the homography found from the given corners applied to the true corners (with noise, the
  noisy corners themselves are not rectangles under any homography, so they cannot measure it);
- centre error: the largest footprint-centre error after the best similarity to the true ground
  coordinates (Umeyama, with scale, no reflection), in % of the extent (diagonal of the footprints'
  bounding box);
- time: per image, rectify() only. Medians and 95th percentiles over frames; best of --repeats for time.

The last lines time the polish on crowded images (--crowd detections each, 2 px of noise): the
exact Jacobian against scipy's finite differences, in one run, and the largest difference between
the homographies the two give.

    .venv/bin/python benchmarks/bench_bev.py
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.detector.bev.homography import apply_homography, rectify, right_angle_error_deg  # noqa: E402
from omnigen.detector.bev.synthetic import centre_error_pct, synthetic_frame  # noqa: E402

TARGETS = {0.0: (0.5, 1.0), 2.0: (3.0, None)}  # noise px -> (right angle deg, centre % of extent)


def measure(frames, noise: float, seed: int, refine: bool) -> tuple[np.ndarray, np.ndarray, float]:
    rng = np.random.default_rng(seed)
    angles, centres, seconds = [], [], 0.0
    for f in frames:
        seen = f.pixels + (rng.normal(0, noise, f.pixels.shape) if noise else 0.0)
        t = time.perf_counter()
        res = rectify(seen, f.classes, refine=refine)
        seconds += time.perf_counter() - t
        exact = apply_homography(res.homography, f.pixels)
        angles.append(float(np.median(right_angle_error_deg(exact))))
        centres.append(centre_error_pct(exact, f.world))
    return np.array(angles), np.array(centres), seconds / len(frames)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3, help="timing runs (accuracy is deterministic)")
    ap.add_argument("--no-refine", action="store_true", help="L_rect only, without the reprojection polish")
    ap.add_argument("--crowd", type=int, nargs="*", default=[20, 50],
                    help="detections an image in the polish's timings (none: skip them)")
    ap.add_argument("--crowd-frames", type=int, default=10)
    args = ap.parse_args()

    rng = np.random.default_rng(args.seed)
    frames = [synthetic_frame(rng) for _ in range(args.frames)]
    n_obj = sum(len(f.pixels) for f in frames)
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}")
    print(f"{len(frames)} synthetic frames, {n_obj} footprints, seed {args.seed}, "
          f"{'L_rect only' if args.no_refine else 'L_rect + reprojection polish'}")
    for noise, (t_angle, t_centre) in TARGETS.items():
        times = []
        for _ in range(args.repeats):
            angles, centres, sec = measure(frames, noise, args.seed + 1, not args.no_refine)
            times.append(sec)
        tc = f"; target < {t_centre}%" if t_centre is not None else " (no target)"
        print(f"noise {noise:g} px: right-angle error median {np.median(angles):.3f} deg, p95 "
              f"{np.percentile(angles, 95):.3f} deg (target < {t_angle} deg); centre error median "
              f"{np.median(centres):.3f}%, p95 {np.percentile(centres, 95):.3f}% of extent{tc}; "
              f"time {1000 * statistics.median(times):.1f} ms/image (median of {args.repeats} runs)")

    for n in [] if args.no_refine else args.crowd:
        crowd(n, args.crowd_frames, args.seed)


def crowd(n: int, frames: int, seed: int) -> None:
    """Median time of rectify() on images of `n` detections (2 px noise), exact Jacobian against
    finite differences, and the largest difference of their homographies."""
    rng = np.random.default_rng(seed)
    times: dict[str, list[float]] = {"exact": [], "2-point": []}
    worst = 0.0
    for _ in range(frames):
        f = synthetic_frame(rng, n=n)
        seen = f.pixels + rng.normal(0, 2.0, f.pixels.shape)
        found = {}
        for jacobian in times:
            t = time.perf_counter()
            found[jacobian] = rectify(seen, f.classes, jacobian=jacobian).homography
            times[jacobian].append(time.perf_counter() - t)
        worst = max(worst, float(np.abs(found["exact"] - found["2-point"]).max()))
    exact, fd = statistics.median(times["exact"]), statistics.median(times["2-point"])
    print(f"{frames} images of {n} detections (2 px): rectify with the polish {exact:.3f} s/image (exact "
          f"Jacobian) against {fd:.3f} s/image (finite differences), {fd / exact:.1f}x; largest homography "
          f"difference {worst:.1e}")


if __name__ == "__main__":
    main()
