"""Training throughput in images/s: the loader alone, the step alone, and end to end (issue 24).

Three numbers say where a training run's time goes:
- the loader alone: the run's own loader (detector/train_loader.py: one for the run, uint8
  batches, pinned on CUDA) iterated without training, in total and per worker process, and the
  samples/s one process makes (decode, letterbox, augment), the most a worker can give;
- the step alone: forward, loss, backward, optimiser and EMA (detector/train_step.py) on one batch
  already on the device, repeated;
- end to end: the loader feeding the step, as `omnigen train` runs it.
End to end near the step alone means the device is the limit; near the loader alone, the loader.
On CUDA it also prints the top operators of a torch.profiler trace of a few steps.

Why each loader measurement builds its own loader and discards its first PREFETCH * workers
batches: iterating a loader queues that many batches at once, and the workers decode them while
nothing is timed (or, for the loader left running, while the step alone is timed). Timing them
would count batches decoded before the clock started; the timed batches are the `--steps` after
them, which the workers decode while the clock runs. Keep --steps well above PREFETCH * workers:
the workers have up to that many batches part-decoded when the clock starts. The step alone runs
with no loader alive, so no worker competes with it for the CPU.

Without --dataset it writes a small fake dataset whose images are textured (a smooth random
pattern, 960x540 PNG unless --fake-size says otherwise), so decoding costs what a render's does.

    .venv/bin/python benchmarks/bench_train_throughput.py --device cpu --imgsz 320 --batch 8 --steps 12 --workers 1
    python benchmarks/bench_train_throughput.py --device cuda --imgsz 640 --batch 64 --workers 14 --dataset D

The last line is `end-to-end: X img/s`.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.detector.data import Augment, KeypointDataset, split_frames  # noqa: E402
from omnigen.detector.ema import ModelEMA  # noqa: E402
from omnigen.detector.loss import DetectionLoss  # noqa: E402
from omnigen.detector.model import DetectorConfig, KeypointDetector  # noqa: E402
from omnigen.detector.train import TrainConfig, autocast_dtype, make_optimizer  # noqa: E402
from omnigen.detector.train_loader import PREFETCH, EpochBatches, make_loader  # noqa: E402
from omnigen.detector.train_step import TrainStep, to_device, use_channels_last  # noqa: E402
from omnigen.taxonomy import load_taxonomy  # noqa: E402


def write_textured_dataset(root: Path, frames: int, width: int, height: int, seed: int = 0) -> Path:
    """A finalized fake dataset (omnigen.fakes geometry) whose images are smooth random textures."""
    import cv2

    from omnigen.writer import DatasetWriter
    from omnigen.fakes import random_frame

    rng = np.random.default_rng(seed)
    writer = DatasetWriter(root, durable=False)
    (root / "images").mkdir(parents=True, exist_ok=True)
    views = ("ego", "infrastructure", "aerial")
    for i in range(frames):
        rec = random_frame(seed, i, "synthetic", views[i % 3], n_objects=8, width=width, height=height)
        coarse = rng.integers(0, 256, (height // 8, width // 8, 3), dtype=np.uint8)
        texture = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
        texture = np.clip(texture.astype(np.int16) + rng.integers(-12, 13, texture.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(root / rec.image), texture)
        for rel in (rec.synthetic.depth, rec.synthetic.instance):
            (root / rel).parent.mkdir(exist_ok=True)
            (root / rel).write_bytes(b"placeholder")
        writer.write(rec)
    writer.finalize({"name": "bench-train-throughput"})
    return root


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="cpu or cuda")
    ap.add_argument("--imgsz", type=int, default=640)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--workers", type=int, default=min(16, os.cpu_count() or 1), help="loader processes")
    ap.add_argument("--steps", type=int, default=10,
                    help="timed batches of each measurement (after the PREFETCH * workers discarded ones)")
    ap.add_argument("--dataset", default=None, help="dataset folder (default: a fake one, written to a temporary folder)")
    ap.add_argument("--frames", type=int, default=None, help="frames of the fake dataset (default: 2 batches, at least 16)")
    ap.add_argument("--fake-size", default="960x540", help="WxH of the fake dataset's images")
    ap.add_argument("--model", default="n")
    ap.add_argument("--no-p2", action="store_true")
    ap.add_argument("--width", type=float, default=None, help="override of the scale's width (tiny test models)")
    ap.add_argument("--depth", type=float, default=None)
    ap.add_argument("--crop", type=int, default=None)
    ap.add_argument("--cache", action="store_true", help="letterboxed images in memory, as train --cache")
    ap.add_argument("--amp", default="auto", choices=["auto", "bf16", "fp16", "off"])
    ap.add_argument("--channels-last", action=argparse.BooleanOptionalAction, default=None)
    ap.add_argument("--threads", type=int, default=None, help="torch threads of the main process")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    with tempfile.TemporaryDirectory() as tmp:
        root = args.dataset
        if root is None:
            w, h = (int(v) for v in args.fake_size.split("x"))
            frames = args.frames or max(16, 2 * args.batch)
            start = time.perf_counter()
            root = write_textured_dataset(Path(tmp) / "fake", frames, w, h)
            print(f"fake dataset: {frames} frames of {w}x{h} in {time.perf_counter() - start:.1f} s")
        run(args, device, root)


def run(args: argparse.Namespace, device: torch.device, root: str | Path) -> None:
    taxonomy = load_taxonomy("fine")
    data = KeypointDataset(root, taxonomy, args.imgsz, split_frames(root, "train"), Augment(), crop=args.crop)
    if args.cache:
        data.cache_images()
    print(f"{len(data)} training frames at {args.imgsz} px{f', {args.crop} px crops' if args.crop else ''}, "
          f"batch {args.batch}, {args.workers} workers, device {device}")

    # one process: what a loader worker can give at most
    n_one = min(len(data), max(8, args.batch))
    start = time.perf_counter()
    for i in range(n_one):
        data[i]
    one = n_one / (time.perf_counter() - start)

    def loader() -> Iterator:
        return iter(make_loader(data, EpochBatches(len(data), args.batch, 0), args.workers, pin=device.type == "cuda"))

    prefetched = PREFETCH * args.workers
    stream = loader()
    loader_rate = timed_rate(stream, prefetched, args.steps, device)
    images, targets, _ = next(stream)  # the step alone's batch
    del stream  # its workers end: none decodes while the step alone is timed

    cfg = DetectorConfig(args.model, p2=not args.no_p2, num_classes=len(taxonomy.classes),
                         width=args.width, depth=args.depth)
    channels_last = use_channels_last(args.channels_last, device)
    model = KeypointDetector(cfg).to(device, memory_format=torch.channels_last if channels_last else torch.preserve_format)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
    model.train()
    amp_dtype = autocast_dtype(args.amp, device)
    step = TrainStep(model, model, DetectionLoss(cfg.num_classes), make_optimizer(TrainConfig(dataset="", out=""), model),
                     torch.amp.GradScaler(device.type, enabled=amp_dtype == torch.float16),
                     ModelEMA(model, 0.9999, 2000.0), amp_dtype)

    on_device = to_device(images, targets, device, channels_last)
    for _ in range(3):  # warm-up: kernel selection (cudnn autotuning, oneDNN primitives)
        step(*on_device)
    sync(device)
    times = []
    for _ in range(args.steps):
        start = time.perf_counter()
        step(*on_device)
        sync(device)
        times.append(time.perf_counter() - start)
    step_rate = len(images) / statistics.median(times)

    end_to_end = timed_rate(loader(), prefetched, args.steps, device,
                            lambda images, targets: step(*to_device(images, targets, device, channels_last)))

    if device.type == "cuda":
        profile(step, on_device, device)
    workers = max(1, args.workers)
    print("| stage | img/s |")
    print("|---|---|")
    print(f"| loader, one process (no loader) | {one:.1f} |")
    print(f"| loader, {args.workers} workers: total | {loader_rate:.1f} |")
    print(f"| loader, per worker | {loader_rate / workers:.1f} |")
    print(f"| step alone (batch on the device, median of {args.steps}) | {step_rate:.1f} |")
    print(f"| end to end | {end_to_end:.1f} |")
    print(f"each loader measurement discarded its first {prefetched} batches (prefetched before timing), "
          f"then timed {args.steps}")
    print(f"end-to-end: {end_to_end:.1f} img/s")


def timed_rate(stream: Iterator, skip: int, steps: int, device: torch.device,
               use: Callable[[torch.Tensor, dict], object] | None = None) -> float:
    """Images/s of `steps` batches of a fresh loader's `stream`, each given to `use` (the step, or
    nothing for the loader alone), after discarding the first `skip`: those were queued when the
    loader was iterated and decoded before the clock started."""
    for _ in range(skip):
        next(stream)
    sync(device)
    start = time.perf_counter()
    count = 0
    for _ in range(steps):
        images, targets, _ = next(stream)
        if use is not None:
            use(images, targets)
        count += len(images)
    sync(device)
    return count / (time.perf_counter() - start)


def profile(step: TrainStep, batch: tuple, device: torch.device, steps: int = 5) -> None:
    """The top operators of a few steps by device time (torch.profiler)."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as trace

    with trace(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            step(*batch)
        sync(device)
    print(f"top operators of {steps} steps by their own CUDA time (torch.profiler)")
    print(prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=15))


if __name__ == "__main__":
    main()
