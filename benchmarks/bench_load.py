"""Loading speed of a dataset folder: 40,000 frames with 300,000 objects (target: under 2 s).

Generates the dataset once (cached in the temp folder, reused when present), then times
`Dataset.open` on it: the path every command takes. Prints the median of --repeats runs and the
one-time cost of rebuilding the index from the per-frame records.

    .venv/bin/python benchmarks/bench_load.py
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import fake_dataset  # noqa: E402
from omnigen.dataset import Dataset  # noqa: E402
from omnigen.index import INDEX_FILE  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40_000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    root = fake_dataset(f"load-{args.frames}", args.frames, images=False)

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
