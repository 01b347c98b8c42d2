"""The statistics report on 40,000 frames with 300,000 objects (target: under 20 s, gallery aside).

Times `omnigen stats` as a person runs it, minus the two steps that read a file per frame or per
picture: opening the dataset, computing every section (overall, per source, per view) and the
health checks on the columns, drawing every figure, writing stats.json and index.html. Figures
are drawn by one process (--jobs 1) unless told otherwise, so the figure holds on one core.
Then, apart: the image-header check on a dataset with real image files, and a gallery of six.

    .venv/bin/python benchmarks/bench_stats.py
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
from omnigen.dataset import Dataset  # noqa: E402
from omnigen.stats.gallery import write_gallery  # noqa: E402
from omnigen.stats.health import image_checks  # noqa: E402
from omnigen.stats.report import write_report  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=1, help="processes drawing figures")
    args = ap.parse_args()

    root = fake_dataset(f"load-{args.frames}", args.frames, images=False)
    Dataset.open(root)  # index current, page cache warm
    work = Path(tempfile.mkdtemp(dir=CACHE))
    totals, steps = [], []
    try:
        for r in range(args.repeats):
            t = time.perf_counter()
            ds = Dataset.open(root)
            opened = time.perf_counter() - t
            result = write_report(ds, work / f"report-{r}", gallery=0, check_images=False, jobs=args.jobs,
                                  show_progress=False)
            totals.append(time.perf_counter() - t)
            steps.append({"open": opened, **{k: v for k, v in result.timings.items() if k != "gallery"}})
        gallery_t = time.perf_counter()
        write_gallery(ds, work / "gallery", 6)
        gallery_t = time.perf_counter() - gallery_t

        with_images = fake_dataset("merge-synthetic-28000", 28_000, "synthetic", seed=1)
        ds_img = Dataset.open(with_images)
        t = time.perf_counter()
        checks = image_checks(ds_img, show_progress=False)
        images_t = time.perf_counter() - t
    finally:
        shutil.rmtree(work, ignore_errors=True)

    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}")
    print(f"dataset: {len(ds)} frames, {len(ds.objects)} objects; {result.figures} figures; jobs {args.jobs}")
    median = statistics.median(totals)
    i = totals.index(median)
    print(f"omnigen stats (open, statistics, health, figures, page; no gallery, no image check): median {median:.2f} s "
          f"over {len(totals)} runs (min {min(totals):.2f}, max {max(totals):.2f}); target < 20 s")
    print("  median run: " + ", ".join(f"{k} {v:.2f} s" for k, v in steps[i].items()))
    print(f"gallery of 6 frames: {gallery_t:.2f} s")
    opened = checks[0]["checked"]
    print(f"image-header check: {opened} images in {images_t:.2f} s "
          f"({1000 * images_t / max(opened, 1):.3f} ms per image; unreadable {checks[0]['count']})")


if __name__ == "__main__":
    main()
