"""What `omnigen train --cache` saves: the training loader's seconds per epoch with the images read
from disk against decoded once into memory.

The loader is timed alone (no model), as `omnigen train` runs it: the train split, letterboxed to
`--imgsz`, random `--crop` windows, the default augmentation, `--workers` processes, batches of 16.
On a machine with few cores the loader's work competes with the training step for the same
cores, so the seconds it saves are seconds of CPU given back to the step. The two modes alternate
epoch by epoch, so a busy machine slows both alike; the script prints each one's median, their
ratio, what building the cache cost once and the memory it holds.

    .venv/bin/python benchmarks/bench_cache.py runs/validate/uov            # make validate's data
    .venv/bin/python benchmarks/bench_cache.py DATASET --imgsz 320 --crop 0 --epochs 5
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.detector.data import Augment, KeypointDataset, collate, split_frames  # noqa: E402
from omnigen.progress import print_table  # noqa: E402
from omnigen.taxonomy import load_taxonomy  # noqa: E402


def epoch_seconds(data: KeypointDataset, epoch: int, workers: int, batch: int) -> float:
    data.set_epoch(epoch)
    loader = torch.utils.data.DataLoader(data, batch_size=batch, shuffle=True, num_workers=workers,
                                         collate_fn=collate, generator=torch.Generator().manual_seed(epoch))
    start = time.perf_counter()
    for _ in loader:
        pass
    return time.perf_counter() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path, help="an UrbanOmniView dataset (its train split is read)")
    ap.add_argument("--imgsz", type=int, default=640)
    ap.add_argument("--crop", type=int, default=320, help="0: whole images")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--epochs", type=int, default=3, help="epochs per mode")
    args = ap.parse_args()
    if not (args.dataset / "manifest.json").exists():
        raise SystemExit(f"bench_cache: {args.dataset}/manifest.json: not a dataset (make validate writes runs/validate/uov)")

    tax = load_taxonomy("fine")
    ids = split_frames(args.dataset, "train")
    crop = args.crop or None
    disk = KeypointDataset(args.dataset, tax, args.imgsz, ids, Augment(), crop=crop)
    ram = KeypointDataset(args.dataset, tax, args.imgsz, ids, Augment(), crop=crop)
    start = time.perf_counter()
    held = ram.cache_images()
    build = time.perf_counter() - start
    times: dict[str, list[float]] = {"disk": [], "memory": []}
    for epoch in range(args.epochs):
        for name, data in (("disk", disk), ("memory", ram)):
            times[name].append(epoch_seconds(data, epoch, args.workers, args.batch))
    med = {k: statistics.median(v) for k, v in times.items()}
    print_table(f"bench_cache: {args.dataset}, {len(disk)} train frames, imgsz {args.imgsz}, crop {crop}, "
                f"{args.workers} worker(s), median of {args.epochs} alternating epochs",
                ["measure", "value"],
                [("loader s/epoch, images from disk", f"{med['disk']:.2f}"),
                 ("loader s/epoch, images in memory (--cache)", f"{med['memory']:.2f}"),
                 ("ratio memory / disk", f"{med['memory'] / med['disk']:.2f}"),
                 ("building the cache once (s)", f"{build:.1f}"),
                 ("memory held (MiB)", f"{held / 2**20:.0f}")])


if __name__ == "__main__":
    main()
