"""Merge 40,000 frames with 300,000 objects, then export them to COCO and YOLO (targets: < 30 s each).

Two fake sources (28,000 synthetic frames from three views, 12,000 KITTI-like frames) with tiny
images, merged with hard links into a fresh folder, then exported. Prints each step's median over
--repeats runs.

    .venv/bin/python benchmarks/bench_merge_export.py
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import CACHE, fake_dataset  # noqa: E402
from omnigen.formats.coco import export_coco  # noqa: E402
from omnigen.dataset import Dataset  # noqa: E402
from omnigen.merge import merge  # noqa: E402
from omnigen.formats.yolo import export_yolo  # noqa: E402


def timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    syn = fake_dataset("merge-synthetic-28000", 28_000, "synthetic", seed=1)
    kit = fake_dataset("merge-kitti-12000", 12_000, "kitti", seed=2)
    work = Path(tempfile.mkdtemp(dir=CACHE))
    results: dict[str, list[float]] = {"merge": [], "export coco": [], "export yolo": []}
    try:
        for r in range(args.repeats):
            out = work / f"uov-{r}"
            results["merge"].append(timed(lambda: merge([syn, kit], out, link="hardlink")))
            results["export coco"].append(timed(lambda: export_coco(Dataset.open(out), work / f"coco-{r}.json")))
            results["export yolo"].append(timed(lambda: export_yolo(Dataset.open(out), work / f"yolo-{r}")))
            ds = Dataset.open(out)
            shutil.rmtree(work / f"yolo-{r}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}")
    print(f"dataset: {len(ds)} frames, {len(ds.objects)} objects, hard links")
    for step, times in results.items():
        print(f"{step}: median {statistics.median(times):.2f} s over {len(times)} runs "
              f"(min {min(times):.2f}, max {max(times):.2f}); target < 30 s")


if __name__ == "__main__":
    main()
