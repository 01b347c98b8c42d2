"""Loading speed of a dataset folder: 40,000 frames with 300,000 objects (target: under 2 s).

Generates the dataset once (cached under --cache, reused when present), then times
`Dataset.open` on it: the path every command takes. Prints the median of --repeats runs and the
one-time cost of rebuilding the index from the per-frame records.

    .venv/bin/python benchmarks/bench_load.py
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
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.dataset import INDEX_FILE, Dataset, DatasetWriter  # noqa: E402
from omnigen.fakes import random_frame  # noqa: E402

VIEWS = ("ego", "infrastructure", "aerial")


def _write_range(args: tuple[str, int, int, int]) -> int:
    root, start, stop, seed = args
    writer = DatasetWriter(root)
    n = 0
    for i in range(start, stop):
        rec = random_frame(seed, i, "synthetic", VIEWS[i % 3], n_objects=8 if i % 2 else 7)
        writer.write(rec)
        n += len(rec.objects)
    return n


def generate(root: Path, frames: int, seed: int = 0, workers: int = 2) -> None:
    chunk = 1000
    jobs = [(str(root), s, min(s + chunk, frames), seed) for s in range(0, frames, chunk)]
    with ProcessPoolExecutor(workers) as pool:
        list(pool.map(_write_range, jobs))
    DatasetWriter(root).finalize({"name": f"bench-load-{frames}"}, show_progress=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "omnigen-bench")
    args = ap.parse_args()

    root = args.cache / f"load-{args.frames}"
    if not (root / "manifest.json").exists():
        shutil.rmtree(root, ignore_errors=True)
        t = time.perf_counter()
        generate(root, args.frames)
        print(f"generated {args.frames} frames in {time.perf_counter() - t:.1f} s at {root}")

    Dataset.open(root)  # make sure the index is current (and warm the page cache)
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        ds = Dataset.open(root)
        times.append(time.perf_counter() - t)
    (root / INDEX_FILE).unlink()
    t = time.perf_counter()
    Dataset.open(root, show_progress=False)
    rebuild = time.perf_counter() - t

    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}")
    print(f"dataset: {len(ds)} frames, {len(ds.objects)} objects")
    print(f"Dataset.open (index current): median {statistics.median(times):.3f} s over {args.repeats} runs "
          f"(min {min(times):.3f}, max {max(times):.3f}); target < 2 s")
    print(f"index rebuild from {len(ds)} record files (once, after records change): {rebuild:.1f} s")


if __name__ == "__main__":
    main()
