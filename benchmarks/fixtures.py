"""Large fake datasets for the benchmarks, generated once and cached between runs.

The frames come from omnigen.fakes (real geometry, random scenes), written by two processes.
Objects per frame alternate 7 and 8, so 40,000 frames hold 300,000 objects.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from PIL import Image  # noqa: E402

from omnigen.writer import DatasetWriter  # noqa: E402
from omnigen.fakes import random_frame  # noqa: E402

CACHE = Path(tempfile.gettempdir()) / "omnigen-bench"
VIEWS = {"synthetic": ("ego", "infrastructure", "aerial"), "kitti": ("ego",), "dair-v2x-i": ("infrastructure",)}


def _write_range(args: tuple[str, str, int, int, int, bool]) -> None:
    root, source, start, stop, seed, images = args
    writer = DatasetWriter(root, durable=False)
    views = VIEWS[source]
    for i in range(start, stop):
        rec = random_frame(seed, i, source, views[i % len(views)], n_objects=8 if i % 2 else 7,
                           width=64, height=40)
        if images:
            Image.new("RGB", (rec.width, rec.height), (i % 251, (i // 251) % 251, seed % 251)).save(Path(root) / rec.image)
            if rec.synthetic is not None:
                for rel in (rec.synthetic.depth, rec.synthetic.instance):
                    (Path(root) / rel).write_bytes(f"{rel}".encode())
        writer.write(rec)


def fake_dataset(name: str, frames: int, source: str = "synthetic", seed: int = 0, images: bool = True) -> Path:
    """A finalized fake dataset under the benchmark cache (generated on first use)."""
    root = CACHE / name
    if (root / "manifest.json").exists():
        return root
    shutil.rmtree(root, ignore_errors=True)
    for sub in ("images", "depth", "instance"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    jobs = [(str(root), source, s, min(s + 1000, frames), seed, images) for s in range(0, frames, 1000)]
    with ProcessPoolExecutor(2) as pool:
        list(pool.map(_write_range, jobs))
    DatasetWriter(root).finalize({"name": name}, show_progress=True)
    print(f"generated {name}: {frames} frames in {time.perf_counter() - t:.1f} s at {root}")
    return root
