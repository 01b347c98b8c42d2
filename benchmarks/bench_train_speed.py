"""Training speed of the detector: one training step, a run's images/s, and the image cache.

- `step`: seconds per training step in float32 and with bf16 autocast (`--amp bf16`). A step is
  what `omnigen train` does per batch: forward, DetectionLoss (always float32), backward, gradient
  clipping and an Adam step, on a real batch (a fake dataset's frames through the training loader).
  `--loop` also times the training loop's whole per-step work as `omnigen train` runs it
  (detector/training/step.py: the uint8 batch converted where the step runs, the step, the fused
  EMA update, the loss parts summed) in float32, with contiguous and with channels-last
  activations. `--overfit` also prints what bf16 costs in
  precision: the overfit check of the test suite (a tiny model, four raster frames of the tiny
  city at 256x192, 700 Adam steps on one thread) trained in each precision, with its final losses
  and OKS mAP50:95 on those frames.
- `throughput`: where the time of a run goes, in images/s: the loader alone (the run's own loader,
  detector/data/loader.py, iterated without training: in total, per worker process, and what one
  process makes without a loader, the most a worker can give), the step alone (on one batch already
  on the device, repeated) and end to end (the loader feeding the step, as `omnigen train` runs
  it). End to end near the step alone means the device is the limit; near the loader alone, the
  loader. On CUDA it also prints the top operators of a torch.profiler trace of a few steps.
  Without --dataset it writes a small fake dataset whose images are textured (a smooth random
  pattern, 960x540 PNG unless --fake-size says otherwise), so decoding costs what a render's does.
  Its last line is `end-to-end: X img/s`, unless `--compare-workers 0,1` follows: end to end with each
  loader-worker count in alternating rounds: on a 2-core CPU, the loader in the step's own process
  against one worker process, the choice `omnigen train` makes by default (loader.loader_workers).
- `cache`: what `omnigen train --cache` saves: the training loader's seconds per epoch with the
  images read from disk against decoded once into memory, timed alone (no model) as `omnigen train`
  runs it (the train split, letterboxed, random --crop windows, the default augmentation). On a
  machine with few cores the loader's work competes with the step for the same cores, so the
  seconds it saves are seconds of CPU given back to the step. Also what building the cache cost
  once and the memory it holds.

What is compared is measured in turn, round by round (alternating_medians), so a busy machine slows
each alike; each one's median and the ratio of the medians are printed.

    .venv/bin/python benchmarks/bench_train_speed.py step               # nano P2, batch 16, 320 px, 2 threads
    .venv/bin/python benchmarks/bench_train_speed.py step --loop        # + the loop, channels-last or not
    .venv/bin/python benchmarks/bench_train_speed.py step --overfit     # + the precision cost (about 5 min)
    .venv/bin/python benchmarks/bench_train_speed.py throughput --device cpu --imgsz 320 --batch 8 --steps 12 --workers 1
    .venv/bin/python benchmarks/bench_train_speed.py throughput --device cpu --dataset runs/validate/uov --recipe \
        --amp bf16 --steps 12 --workers 1 --compare-workers 0,1 [--cache]   # make validate's step and data
    python benchmarks/bench_train_speed.py throughput --device cuda --imgsz 640 --batch 64 --workers 14 --dataset D
    .venv/bin/python benchmarks/bench_train_speed.py cache runs/validate/uov   # make validate's data
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.detector.data.samples import Augment, KeypointDataset, collate, split_frames  # noqa: E402
from omnigen.detector.training.ema import ModelEMA  # noqa: E402
from omnigen.detector.training.loss import DetectionLoss  # noqa: E402
from omnigen.detector.model.network import DetectorConfig, KeypointDetector  # noqa: E402
from omnigen.detector.recipe import RECIPE, train_fields  # noqa: E402
from omnigen.detector.training.train import (TrainConfig, autocast_dtype, detection_loss, fast_bf16,  # noqa: E402
                                             make_optimizer, training_data)
from omnigen.detector.data.loader import PREFETCH, EpochBatches, collate_uint8, make_loader  # noqa: E402
from omnigen.detector.training.step import PartSums, TrainStep, to_device, use_channels_last  # noqa: E402
from omnigen.options import integer, number  # noqa: E402
from omnigen.taxonomy import load_taxonomy  # noqa: E402

MODES = ("off", "bf16")
VARIANTS = ("contiguous", "channels-last")


def alternating_medians(measures: dict[str, Callable[[int], float]], rounds: int) -> dict[str, float]:
    """Each measurement's median seconds over `rounds`, all of them taken in turn within a round
    (measure(round) returns its seconds), so that a machine busy for a while slows each alike."""
    times: dict[str, list[float]] = {name: [] for name in measures}
    for r in range(rounds):
        for name, measure in measures.items():
            times[name].append(measure(r))
    return {name: statistics.median(t) for name, t in times.items()}


def detector(args: argparse.Namespace, num_classes: int) -> KeypointDetector:
    """The model the options name (--model, --no-p2, and --width/--depth for tiny test models)."""
    return KeypointDetector(DetectorConfig(args.model, p2=not args.no_p2, num_classes=num_classes,
                                           width=args.width, depth=args.depth))


def precision_name(amp: str) -> str:
    return "float32" if amp == "off" else amp


def train_step(model: KeypointDetector, amp_dtype: torch.dtype | None, cfg: TrainConfig | None = None) -> TrainStep:
    """A TrainStep as `omnigen train` builds it, on `model` where it is: the recipe's optimiser and
    EMA (TrainConfig's defaults), a gradient scaler for fp16 only; the loss is `cfg`'s (the
    recipe's gains, `--recipe`), else the design's gains (LossGains()), as the step timings always had."""
    loss = detection_loss(cfg, model) if cfg is not None else DetectionLoss(model.cfg.num_classes)
    cfg = cfg or TrainConfig(dataset="", out="")
    device = next(model.parameters()).device
    return TrainStep(model, model, loss, make_optimizer(cfg, model),
                     torch.amp.GradScaler(device.type, enabled=amp_dtype == torch.float16),
                     ModelEMA(model, cfg.ema_decay, cfg.ema_tau), amp_dtype)


# ---------------------------------------------------------------------------------------------
# step: float32 against bf16, the loop before and after issue 24, the overfit check
# ---------------------------------------------------------------------------------------------


def run_step(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    device = torch.device("cpu")
    taxonomy = load_taxonomy("fine")
    with tempfile.TemporaryDirectory() as tmp:
        from omnigen.fakes import write_fake_dataset

        write_fake_dataset(tmp, args.batch, objects_per_frame=8, seed=0)
        data = KeypointDataset(tmp, taxonomy, args.imgsz, None, Augment())
        batch = [data[i] for i in range(args.batch)]
        images, targets, _ = collate(batch)

    model = detector(args, len(taxonomy.classes))
    model.train()
    criterion = DetectionLoss(model.cfg.num_classes)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    dtypes = {amp: autocast_dtype(amp, device) for amp in MODES}  # once: bf16 warns where it is emulated

    def step(amp: str) -> float:
        dtype = dtypes[amp]
        start = time.perf_counter()
        with torch.autocast("cpu", dtype=dtype or torch.float32, enabled=dtype is not None):
            out = model(images)
        loss, _ = criterion(out, targets)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        optimizer.step()
        return time.perf_counter() - start

    for amp in MODES:  # warm-up: oneDNN picks its kernels on the first calls
        step(amp), step(amp)
    med = alternating_medians({amp: lambda _, amp=amp: step(amp) for amp in MODES}, args.steps)
    p2 = "" if args.no_p2 else " P2"
    print(f"train step, model {args.model}{p2}, batch {args.batch}, {args.imgsz} px, {args.threads} threads, "
          f"native bf16: {fast_bf16(device)}; median of {args.steps} alternating steps")
    print("| precision | s per step | images/s |")
    print("|---|---|---|")
    for amp in MODES:
        print(f"| {precision_name(amp)} | {med[amp]:.3f} | {args.batch / med[amp]:.1f} |")
    print(f"bf16 / float32 step time: {med['bf16'] / med['off']:.2f}")
    if args.loop:
        loop(args, model.cfg, batch)
    if args.overfit:
        overfit()


def loop_step(model: torch.nn.Module, uint8_batch: tuple, channels_last: bool) -> Callable[[], None]:
    """One step of the loop as `omnigen train` runs it (detector/training/step.py)."""
    step = train_step(model, None)
    sums = PartSums()
    return lambda: sums.add(step(*to_device(*uint8_batch, torch.device("cpu"), channels_last)))


def loop(args: argparse.Namespace, cfg: DetectorConfig, samples: list) -> None:
    """The loop's per-step work in float32, contiguous and channels-last, alternating step by step."""
    uint8_batch = collate_uint8(samples)[:2]
    steps: dict[str, Callable[[], None]] = {}
    for name in VARIANTS:
        torch.manual_seed(0)
        model = KeypointDetector(cfg)
        if name == "channels-last":
            model = model.to(memory_format=torch.channels_last)
        model.train()
        steps[name] = loop_step(model, uint8_batch, name == "channels-last")
    for name in VARIANTS:  # warm-up
        steps[name](), steps[name]()

    def timed(run: Callable[[], None]) -> Callable[[int], float]:
        def measure(_: int) -> float:
            start = time.perf_counter()
            run()
            return time.perf_counter() - start
        return measure

    med = alternating_medians({name: timed(steps[name]) for name in VARIANTS}, args.steps)
    print(f"training loop step (detector/training/step.py), float32, batch {args.batch}, {args.imgsz} px, "
          f"{args.threads} threads; median of {args.steps} alternating steps")
    print("| activations | s per step | images/s | / contiguous |")
    print("|---|---|---|---|")
    for name in VARIANTS:
        print(f"| {name} | {med[name]:.3f} | {args.batch / med[name]:.1f} | {med[name] / med['contiguous']:.3f} |")


def overfit() -> None:
    """The test suite's overfit run (test_tiny_model_overfits_four_rendered_frames) in both
    precisions, at the size it ran at when the docs' precision row was measured (256 x 192, 700
    steps; the test now runs 128 x 96 and 600 steps to save time)."""
    from omnigen.cli import main as omnigen
    from omnigen.detector.model.checkpoint import plain_branch
    from omnigen.detector.training.train import train

    torch.set_num_threads(1)  # as the test: the trajectory then does not depend on the thread count (on one CPU)
    with tempfile.TemporaryDirectory() as tmp:
        frames = Path(tmp) / "ego"
        rc = omnigen(["render", "--rig", "ego-lane", "--frames", "4", "--out", str(frames), "--seed", "3", "--scene", "tiny",
                      "--width", "256", "--height", "192", "--backend", "raster"])
        if rc != 0:
            raise SystemExit("bench_train_speed: the overfit frames did not render")
        rows = []
        for amp in MODES:
            cfg = TrainConfig(**{**plain_branch(), "dataset": str(frames), "out": str(Path(tmp) / amp), "imgsz": 256,
                                 "batch": 4, "workers": 0, "augment": asdict(Augment.off()), "epochs": 700,
                                 "val_every": 700, "warmup_iters": 20, "optimizer": "adam", "lr0": 2e-2, "amp": amp,
                                 "model": "n", "width": 0.125, "depth": 0.34})
            start = time.perf_counter()
            last = train(cfg)
            rows.append((amp, last, time.perf_counter() - start))
    print("overfit check, 700 steps on four frames, one thread")
    print("| precision | box | kpt | cls | OKS mAP50:95 | seconds |")
    print("|---|---|---|---|---|---|")
    for amp, last, seconds in rows:
        print(f"| {precision_name(amp)} | {last['box']:.3f} | {last['kpt']:.3f} | {last['cls']:.3f} | "
              f"{last['oks_map50_95']:.3f} | {seconds:.0f} |")


# ---------------------------------------------------------------------------------------------
# throughput: the loader alone, the step alone, end to end
# ---------------------------------------------------------------------------------------------
# Why each loader measurement builds its own loader and discards its first PREFETCH * workers
# batches: iterating a loader queues that many batches at once, and the workers decode them while
# nothing is timed (or, for the loader left running, while the step alone is timed). Timing them
# would count batches decoded before the clock started; the timed batches are the --steps after
# them, which the workers decode while the clock runs. Keep --steps well above PREFETCH * workers:
# the workers have up to that many batches part-decoded when the clock starts. The step alone runs
# with no loader alive, so no worker competes with it for the CPU.


def write_textured_dataset(root: Path, frames: int, width: int, height: int, seed: int = 0) -> Path:
    """A finalized fake dataset (omnigen.fakes geometry) whose images are smooth random textures."""
    import cv2

    from omnigen.fakes import random_frame
    from omnigen.writer import DatasetWriter

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


def image_size(text: str) -> tuple[int, int]:
    """--fake-size: WxH, each at least 8 pixels (the texture is drawn at an eighth of the size)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give WIDTHxHEIGHT, e.g. 960x540") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"{text!r}: width and height must be at least 8")
    return w, h


def worker_counts(text: str) -> list[int]:
    """'0,1' -> [0, 1]: two or more distinct counts of loader processes."""
    try:
        counts = [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected worker counts such as 0,1") from None
    if len(counts) < 2 or len(set(counts)) != len(counts) or min(counts) < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: give two or more distinct counts, each 0 or more")
    return counts


def run_throughput(args: argparse.Namespace) -> None:
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    with tempfile.TemporaryDirectory() as tmp:
        root = args.dataset
        if root is None:
            w, h = args.fake_size
            frames = args.frames or max(16, 2 * args.batch)
            start = time.perf_counter()
            root = write_textured_dataset(Path(tmp) / "fake", frames, w, h)
            print(f"fake dataset: {frames} frames of {w}x{h} in {time.perf_counter() - start:.1f} s")
        throughput(args, device, root)


def throughput(args: argparse.Namespace, device: torch.device, root: str | Path) -> None:
    # --recipe: the model, loss, batch and data `omnigen train` builds from the recipe
    cfg = TrainConfig(dataset=str(root), out="", **train_fields(RECIPE)) if args.recipe else None
    if cfg is not None:
        args.imgsz, args.batch, args.crop = cfg.imgsz, cfg.batch, cfg.window()
        taxonomy = load_taxonomy(cfg.taxonomy)
        data = training_data(cfg, taxonomy)
    else:
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

    prefetched = PREFETCH * args.workers
    stream = loader(data, args.batch, args.workers, device)
    loader_rate = timed_rate(stream, prefetched, args.steps, device)
    images, targets, _ = next(stream)  # the step alone's batch
    del stream  # its workers end: none decodes while the step alone is timed

    channels_last = use_channels_last(args.channels_last, device)
    model = KeypointDetector(cfg.model_config(len(taxonomy.classes))) if cfg is not None \
        else detector(args, len(taxonomy.classes))
    model = model.to(device, memory_format=torch.channels_last if channels_last else torch.preserve_format)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
    model.train()
    step = train_step(model, autocast_dtype(args.amp, device), cfg)

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

    end_to_end = end_to_end_rate(data, args, args.workers, device, step, channels_last)

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
    if args.compare_workers:
        compare_workers(args, data, device, step, channels_last)


def loader(data: KeypointDataset, batch: int, workers: int, device: torch.device) -> Iterator:
    """A fresh training loader's batches (detector/data/loader.py), as `omnigen train` iterates them."""
    return iter(make_loader(data, EpochBatches(len(data), batch, 0), workers, pin=device.type == "cuda"))


def end_to_end_rate(data: KeypointDataset, args: argparse.Namespace, workers: int, device: torch.device,
                    step: Callable, channels_last: bool) -> float:
    """Images/s of a fresh loader with `workers` processes feeding the step, --steps batches timed."""
    return timed_rate(loader(data, args.batch, workers, device), PREFETCH * workers, args.steps, device,
                      lambda images, targets: step(*to_device(images, targets, device, channels_last)))


def compare_workers(args: argparse.Namespace, data: KeypointDataset, device: torch.device, step: Callable,
                    channels_last: bool) -> None:
    """End to end with each loader-worker count of --compare-workers, a fresh loader each round and
    the counts in turn round by round (what `omnigen train --workers` chooses between)."""
    counts = args.compare_workers
    rates: dict[int, list[float]] = {n: [] for n in counts}
    for _ in range(args.rounds):
        for n in counts:
            rates[n].append(end_to_end_rate(data, args, n, device, step, channels_last))
    print(f"end to end by loader workers, median of {args.rounds} alternating rounds of {args.steps} steps")
    print("| workers | img/s | against the first |")
    print("|---|---|---|")
    first = statistics.median(rates[counts[0]])
    for n in counts:
        rate = statistics.median(rates[n])
        print(f"| {n} | {rate:.1f} | {rate / first:.2f} |")


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


# ---------------------------------------------------------------------------------------------
# cache: the loader's epoch from disk against from memory (train --cache)
# ---------------------------------------------------------------------------------------------


def epoch_seconds(data: KeypointDataset, epoch: int, workers: int, batch: int) -> float:
    """One epoch of the training loader, as `omnigen train` makes it (make_loader), its workers started."""
    sampler = EpochBatches(len(data), batch, 0, start=epoch)
    batches = iter(make_loader(data, sampler, workers, pin=False))
    start = time.perf_counter()
    for _ in range(sampler.per_epoch()):  # the loader's batches do not end
        next(batches)
    return time.perf_counter() - start


def run_cache(args: argparse.Namespace) -> None:
    from omnigen.progress import print_table

    if not (args.dataset / "manifest.json").exists():
        raise SystemExit(f"bench_train_speed: {args.dataset}/manifest.json: not a dataset "
                         "(make validate writes runs/validate/uov)")
    tax = load_taxonomy("fine")
    ids = split_frames(args.dataset, "train")
    crop = args.crop or None
    disk = KeypointDataset(args.dataset, tax, args.imgsz, ids, Augment(), crop=crop)
    ram = KeypointDataset(args.dataset, tax, args.imgsz, ids, Augment(), crop=crop)
    start = time.perf_counter()
    held = ram.cache_images()
    build = time.perf_counter() - start
    med = alternating_medians({name: lambda epoch, data=data: epoch_seconds(data, epoch, args.workers, args.batch)
                               for name, data in (("disk", disk), ("memory", ram))}, args.epochs)
    print_table(f"bench_train_speed cache: {args.dataset}, {len(disk)} train frames, imgsz {args.imgsz}, crop {crop}, "
                f"{args.workers} worker(s), median of {args.epochs} alternating epochs",
                ["measure", "value"],
                [("loader s/epoch, images from disk", f"{med['disk']:.2f}"),
                 ("loader s/epoch, images in memory (--cache)", f"{med['memory']:.2f}"),
                 ("ratio memory / disk", f"{med['memory'] / med['disk']:.2f}"),
                 ("building the cache once (s)", f"{build:.1f}"),
                 ("memory held (MiB)", f"{held / 2**20:.0f}")])


# ---------------------------------------------------------------------------------------------
# options
# ---------------------------------------------------------------------------------------------


def add_model_options(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--model", default="n", help="detector scale")
    ap.add_argument("--no-p2", action="store_true", help="without the P2 level")
    ap.add_argument("--width", type=number(0, None, lo_open=True), default=None,
                    help="override of the scale's width (tiny test models)")
    ap.add_argument("--depth", type=number(0, None, lo_open=True), default=None, help="override of the scale's depth")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="measure", required=True)

    step = sub.add_parser("step", help="seconds per step, float32 against bf16 (--loop, --overfit)")
    add_model_options(step)
    step.add_argument("--imgsz", type=integer(32, None), default=320)
    step.add_argument("--batch", type=integer(1, None), default=16)
    step.add_argument("--steps", type=integer(1, None), default=15, help="timed steps per precision")
    step.add_argument("--threads", type=integer(1, None), default=2)
    step.add_argument("--loop", action="store_true", help="also time the loop's per-step work, contiguous and channels-last")
    step.add_argument("--overfit", action="store_true", help="also train the overfit check in both precisions")
    step.set_defaults(run=run_step)

    tp = sub.add_parser("throughput", help="images/s of the loader alone, the step alone and end to end")
    add_model_options(tp)
    tp.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="cpu or cuda")
    tp.add_argument("--imgsz", type=integer(32, None), default=640)
    tp.add_argument("--batch", type=integer(1, None), default=64)
    tp.add_argument("--workers", type=integer(0, None), default=min(16, os.cpu_count() or 1), help="loader processes")
    tp.add_argument("--steps", type=integer(1, None), default=10,
                    help="timed batches of each measurement (after the PREFETCH * workers discarded ones)")
    tp.add_argument("--dataset", default=None, help="dataset folder (default: a fake one, written to a temporary folder)")
    tp.add_argument("--frames", type=integer(1, None), default=None,
                    help="frames of the fake dataset (default: 2 batches, at least 16)")
    tp.add_argument("--fake-size", type=image_size, default=(960, 540), help="WxH of the fake dataset's images")
    tp.add_argument("--crop", type=integer(1, None), default=None,
                    help="training windows of this size (the recipe's data.window)")
    tp.add_argument("--cache", action="store_true", help="letterboxed images in memory, as train --cache")
    tp.add_argument("--recipe", action="store_true",
                    help="the model, loss, input, windows, batch and augmentation of the recipe (detector/recipe.py) "
                         "as omnigen train builds them, instead of --model, --imgsz, --crop and --batch")
    tp.add_argument("--amp", default="auto", choices=["auto", "bf16", "fp16", "off"])
    tp.add_argument("--channels-last", action=argparse.BooleanOptionalAction, default=None)
    tp.add_argument("--threads", type=integer(1, None), default=None, help="torch threads of the main process")
    tp.add_argument("--compare-workers", type=worker_counts, default=None, metavar="N,M",
                    help="also time end to end with each of these loader-worker counts, in alternating rounds")
    tp.add_argument("--rounds", type=integer(1, None), default=3, help="rounds of --compare-workers")
    tp.set_defaults(run=run_throughput)

    cache = sub.add_parser("cache", help="the loader's seconds per epoch from disk against in memory (train --cache)")
    cache.add_argument("dataset", type=Path, help="an UrbanOmniView dataset (its train split is read)")
    cache.add_argument("--imgsz", type=integer(32, None), default=640)
    cache.add_argument("--crop", type=integer(0, None), default=320,
                       help="training windows of this size (the recipe's data.window); 0: whole images")
    cache.add_argument("--workers", type=integer(0, None), default=1)
    cache.add_argument("--batch", type=integer(1, None), default=16)
    cache.add_argument("--epochs", type=integer(1, None), default=3, help="epochs per mode")
    cache.set_defaults(run=run_cache)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.run(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
