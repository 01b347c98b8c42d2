"""Benchmark: what checking an image in full costs, against reading its header only.

Converters and `omnigen validate` decode every image (omnigen.images.check_image) instead of
trusting the header: a truncated file keeps its header. This prints, per image kind, the median
milliseconds of one header read (omnigen.images.image_size), one full check (check_image: PNG
verify + decode; JPEG decoded at 1/8 scale) and, for reference, one plain full-scale PIL decode,
with the ratio of the check to the header read.

Images: KITTI's three real frames from ../shared/realdata when present (1242x375 PNG), and
generated ones of DAIR-V2X's size (1920x1080 JPEG at quality 90) and KITTI's (1242x375 PNG): a
smooth gradient with noise, which compresses about as badly as a photograph.

    .venv/bin/python benchmarks/bench_image_check.py [--repeats N]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.images import check_image, image_size  # noqa: E402

REAL_KITTI = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "kitti" / "training" / "image_2"


def generated(path: Path, size: tuple[int, int], fmt: str, seed: int = 0) -> Path:
    w, h = size
    rng = np.random.default_rng(seed)
    ramp = np.linspace(0, 180, w)[None, :, None] + np.linspace(0, 60, h)[:, None, None]
    pixels = np.clip(ramp + rng.normal(0, 12, size=(h, w, 3)), 0, 255).astype(np.uint8)
    Image.fromarray(pixels).save(path, format=fmt, **({"quality": 90} if fmt == "JPEG" else {}))
    return path


def plain_decode(path: Path) -> None:
    with Image.open(path) as im:
        im.load()


def median_ms(fn: Callable[[Path], object], paths: list[Path], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        for p in paths:
            t = time.perf_counter()
            fn(p)
            times.append(time.perf_counter() - t)
    return statistics.median(times) * 1000


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=20)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        kinds = {
            "DAIR-V2X size, generated JPEG 1920x1080": [generated(Path(tmp) / f"d{i}.jpg", (1920, 1080), "JPEG", i)
                                                       for i in range(3)],
            "KITTI size, generated PNG 1242x375": [generated(Path(tmp) / f"k{i}.png", (1242, 375), "PNG", i)
                                                  for i in range(3)],
        }
        real = sorted(REAL_KITTI.glob("*.png")) if REAL_KITTI.is_dir() else []
        if real:
            kinds["KITTI, real frames (shared/realdata)"] = real
        print(f"median ms per image over {args.repeats} repeats, one process (load average {os.getloadavg()[0]:.2f})")
        print(f"{'images':44} {'header':>8} {'check':>8} {'plain decode':>13} {'check/header':>13}")
        for name, paths in kinds.items():
            header = median_ms(image_size, paths, args.repeats)
            check = median_ms(check_image, paths, args.repeats)
            plain = median_ms(plain_decode, paths, args.repeats)
            print(f"{name:44} {header:8.2f} {check:8.2f} {plain:13.2f} {check / header:13.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
