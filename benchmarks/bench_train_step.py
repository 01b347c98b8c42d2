"""Seconds per training step of the detector in float32 and with bf16 autocast (`--amp bf16`).

A step is what `omnigen train` does per batch: forward, DetectionLoss (always float32), backward,
gradient clipping and an Adam step. The batch is real: a fake dataset's frames through the
training loader. The precisions alternate step by step after a warm-up, so a busy machine slows
both alike; the script prints each one's median and the ratio of the medians.

`--loop` also times the training loop's own per-step work as `omnigen train` did it before issue
24 (EMA through two state_dict() walks, float32 images out of the loader) against what it does now
(detector/train_step.py: fused foreach EMA, uint8 batch converted where the step runs), in float32
and with channels-last activations, alternating step by step in one run: medians and their ratio.

`--overfit` also prints what bf16 costs in precision: the overfit check of the test suite (a tiny
model, four raster frames of the tiny city at 256x192, 700 Adam steps on one thread) trained in
each precision, with its final losses and OKS mAP50:95 on those frames.

    .venv/bin/python benchmarks/bench_train_step.py              # nano P2, batch 16, 320 px, 2 threads
    .venv/bin/python benchmarks/bench_train_step.py --imgsz 640 --steps 10
    .venv/bin/python benchmarks/bench_train_step.py --loop       # + the loop: before/after issue 24
    .venv/bin/python benchmarks/bench_train_step.py --overfit    # + the precision cost (about 5 min)
"""

from __future__ import annotations

import argparse
import copy
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.detector.data import Augment, KeypointDataset, collate  # noqa: E402
from omnigen.detector.ema import ModelEMA  # noqa: E402
from omnigen.detector.loss import DetectionLoss  # noqa: E402
from omnigen.detector.model import DetectorConfig, KeypointDetector  # noqa: E402
from omnigen.detector.train import autocast_dtype, fast_bf16  # noqa: E402
from omnigen.fakes import write_fake_dataset  # noqa: E402
from omnigen.taxonomy import load_taxonomy  # noqa: E402

MODES = ("off", "bf16")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="n")
    ap.add_argument("--no-p2", action="store_true")
    ap.add_argument("--imgsz", type=int, default=320)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--steps", type=int, default=15, help="timed steps per precision")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--loop", action="store_true", help="also time the loop's per-step work before/after issue 24")
    ap.add_argument("--overfit", action="store_true", help="also train the overfit check in both precisions")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    device = torch.device("cpu")

    taxonomy = load_taxonomy("fine")
    with tempfile.TemporaryDirectory() as tmp:
        write_fake_dataset(tmp, args.batch, objects_per_frame=8, seed=0)
        data = KeypointDataset(tmp, taxonomy, args.imgsz, None, Augment())
        batch = [data[i] for i in range(args.batch)]
        images, targets, _ = collate(batch)

    model = KeypointDetector(DetectorConfig(args.model, p2=not args.no_p2, num_classes=len(taxonomy.classes)))
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
    times: dict[str, list[float]] = {m: [] for m in MODES}
    for _ in range(args.steps):
        for amp in MODES:
            times[amp].append(step(amp))

    p2 = "" if args.no_p2 else " P2"
    print(f"train step, model {args.model}{p2}, batch {args.batch}, {args.imgsz} px, {args.threads} threads, "
          f"native bf16: {fast_bf16(device)}; median of {args.steps} alternating steps")
    print("| precision | s per step | images/s |")
    print("|---|---|---|")
    med = {m: statistics.median(t) for m, t in times.items()}
    for amp in MODES:
        print(f"| {'float32' if amp == 'off' else amp} | {med[amp]:.3f} | {args.batch / med[amp]:.1f} |")
    print(f"bf16 / float32 step time: {med['bf16'] / med['off']:.2f}")
    if args.loop:
        loop(args, model.cfg, batch)
    if args.overfit:
        overfit()


class LegacyEMA:
    """The EMA update as train.py did it before issue 24: two state_dict() walks a step."""

    def __init__(self, model: torch.nn.Module, decay: float = 0.9999, tau: float = 2000.0):
        self.ema, self.decay, self.tau, self.updates = copy.deepcopy(model).eval(), decay, tau, 0

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        self.updates += 1
        d = self.decay * (1 - math.exp(-self.updates / self.tau))
        msd = model.state_dict()
        for k, v in self.ema.state_dict().items():
            if v.dtype.is_floating_point:
                v.mul_(d).add_(msd[k].detach(), alpha=1 - d)
            else:
                v.copy_(msd[k])


def loop(args: argparse.Namespace, cfg: DetectorConfig, samples: list) -> None:
    """The loop's per-step work, before and after issue 24, float32, alternating step by step."""
    from omnigen.detector.train import TrainConfig, make_optimizer
    from omnigen.detector.train_loader import collate_uint8
    from omnigen.detector.train_step import PartSums, TrainStep, to_device

    device = torch.device("cpu")
    float_batch, uint8_batch = collate(samples)[:2], collate_uint8(samples)[:2]
    steps: dict[str, Callable[[], None]] = {}
    for name in VARIANTS:
        torch.manual_seed(0)
        model = KeypointDetector(cfg)
        if name == "after, channels-last":
            model = model.to(memory_format=torch.channels_last)
        model.train()
        optimizer = make_optimizer(TrainConfig(dataset="", out=""), model)
        criterion = DetectionLoss(cfg.num_classes)
        scaler = torch.amp.GradScaler("cpu", enabled=False)
        if name == "before":
            ema = LegacyEMA(model)

            def before(model=model, optimizer=optimizer, criterion=criterion, ema=ema) -> None:
                images, targets = float_batch
                loss, parts = criterion(model(images), targets)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
                optimizer.step()
                ema.update(model)
                sums = {k: float(v) for k, v in parts.items()}  # a float() per part and step
                assert sums
            steps[name] = before
        else:
            step = TrainStep(model, model, criterion, optimizer, scaler, ModelEMA(model, 0.9999, 2000.0), None)
            sums = PartSums()
            cl = name.endswith("channels-last")
            steps[name] = lambda step=step, sums=sums, cl=cl: sums.add(step(*to_device(*uint8_batch, device, cl)))
    for name in VARIANTS:  # warm-up
        steps[name](), steps[name]()
    times: dict[str, list[float]] = {name: [] for name in VARIANTS}
    for _ in range(args.steps):
        for name in VARIANTS:
            start = time.perf_counter()
            steps[name]()
            times[name].append(time.perf_counter() - start)
    med = {name: statistics.median(t) for name, t in times.items()}
    print(f"training loop step (train_step.py) before/after issue 24, float32, batch {args.batch}, {args.imgsz} px, "
          f"{args.threads} threads; median of {args.steps} alternating steps")
    print("| loop | s per step | images/s | / before |")
    print("|---|---|---|---|")
    for name in VARIANTS:
        print(f"| {name} | {med[name]:.3f} | {args.batch / med[name]:.1f} | {med[name] / med['before']:.3f} |")


VARIANTS = ("before", "after", "after, channels-last")


def overfit() -> None:
    """The test suite's overfit run (test_tiny_model_overfits_four_rendered_frames) in both precisions."""
    from dataclasses import asdict

    from omnigen.detector.train import TrainConfig, train
    from omnigen.cli import main as omnigen

    torch.set_num_threads(1)  # as the test: the trajectory then does not depend on the thread count
    with tempfile.TemporaryDirectory() as tmp:
        frames = Path(tmp) / "ego"
        rc = omnigen(["render", "--rig", "ego-lane", "--frames", "4", "--out", str(frames), "--seed", "3", "--scene", "tiny",
                      "--width", "256", "--height", "192", "--backend", "raster"])
        if rc != 0:
            raise SystemExit("bench_train_step: the overfit frames did not render")
        rows = []
        for amp in MODES:
            cfg = TrainConfig(dataset=str(frames), out=str(Path(tmp) / amp), imgsz=256, batch=4, workers=0,
                              augment=asdict(Augment.off()), epochs=700, val_every=700, warmup_iters=20,
                              optimizer="adam", lr0=2e-2, amp=amp, model="n", width=0.125, depth=0.34)
            start = time.perf_counter()
            last = train(cfg)
            rows.append((amp, last, time.perf_counter() - start))
    print("overfit check, 700 steps on four frames, one thread")
    print("| precision | box | kpt | cls | OKS mAP50:95 | seconds |")
    print("|---|---|---|---|---|---|")
    for amp, last, seconds in rows:
        print(f"| {'float32' if amp == 'off' else amp} | {last['box']:.3f} | {last['kpt']:.3f} | {last['cls']:.3f} | "
              f"{last['oks_map50_95']:.3f} | {seconds:.0f} |")


if __name__ == "__main__":
    main()
