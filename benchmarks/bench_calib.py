"""Lifting speed: PnP lifts per second, what `omnigen calib-sensitivity` spends its time on.

The command lifts every detection once per K it tries (6 by default). The issue sets no target of
its own for this command; the figure printed is the budget it implies: KITTI val (3,769 frames,
about 8 detections each) x 6 intrinsics lifted in under 30 s needs under 165 us per lift.

    .venv/bin/python benchmarks/bench_calib.py
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.detector.lift import lift_keypoints  # noqa: E402
from omnigen.formats.kitti import box_from_kitti  # noqa: E402
from omnigen.geometry import project_points  # noqa: E402

K = np.array([[721.5, 0.0, 609.6], [0.0, 721.5, 172.9], [0.0, 0.0, 1.0]])
TARGET_US = 30.0 / (3769 * 8 * 6) * 1e6


def boxes(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Cars in front of a KITTI camera: exact corners plus 1.5 px noise, and prior-like dims."""
    kps, dims = [], []
    for _ in range(n):
        b = box_from_kitti(1.5, 1.7, 4.1, rng.uniform(-8, 8), 1.65, rng.uniform(6, 50), rng.uniform(-math.pi, math.pi))
        kps.append(project_points(K, b.corners())[0] + rng.normal(0, 1.5, (8, 2)))
        dims.append(b.dims * rng.uniform(0.9, 1.1, 3))
    return np.array(kps), np.array(dims)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boxes", type=int, default=5000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    kp, dims = boxes(args.boxes, np.random.default_rng(0))
    times, ok = [], 0
    for _ in range(args.repeats):
        t = time.perf_counter()
        lifted = lift_keypoints(kp, dims, K)
        times.append(time.perf_counter() - t)
        ok = int(lifted.ok.sum())
    per = statistics.median(times) / args.boxes * 1e6
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}")
    print(f"lift_keypoints on {args.boxes} boxes (1.5 px noise): {ok} lifted; median {statistics.median(times):.3f} s "
          f"over {args.repeats} runs = {per:.1f} us per box; budget < {TARGET_US:.0f} us per box "
          f"(KITTI val x 6 intrinsics in 30 s; the issue sets no target for this command)")


if __name__ == "__main__":
    main()
