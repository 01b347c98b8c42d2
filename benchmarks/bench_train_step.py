"""Seconds per training step of the detector in float32 and with bf16 autocast (`--amp bf16`).

A step is what `omnigen train` does per batch: forward, DetectionLoss (always float32), backward,
gradient clipping and an Adam step. The batch is real: a fake dataset's frames through the
training loader. The precisions alternate step by step after a warm-up, so a busy machine slows
both alike; the script prints each one's median and the ratio of the medians.

`--overfit` also prints what bf16 costs in precision: the overfit check of the test suite (a tiny
model, four raster frames of the tiny city at 256x192, 700 Adam steps on one thread) trained in
each precision, with its final losses and OKS mAP50:95 on those frames.

    .venv/bin/python benchmarks/bench_train_step.py              # nano P2, batch 16, 320 px, 2 threads
    .venv/bin/python benchmarks/bench_train_step.py --imgsz 640 --steps 10
    .venv/bin/python benchmarks/bench_train_step.py --overfit    # + the precision cost (about 5 min)
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from detector.data import Augment, KeypointDataset, collate  # noqa: E402
from detector.loss import DetectionLoss  # noqa: E402
from detector.model import DetectorConfig, KeypointDetector  # noqa: E402
from detector.train import autocast_dtype, fast_bf16  # noqa: E402
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
    ap.add_argument("--overfit", action="store_true", help="also train the overfit check in both precisions")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    device = torch.device("cpu")

    taxonomy = load_taxonomy("fine")
    with tempfile.TemporaryDirectory() as tmp:
        write_fake_dataset(tmp, args.batch, objects_per_frame=8, seed=0)
        data = KeypointDataset(tmp, taxonomy, args.imgsz, None, Augment())
        images, targets, _ = collate([data[i] for i in range(args.batch)])

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
    if args.overfit:
        overfit()


def overfit() -> None:
    """The test suite's overfit run (test_tiny_model_overfits_four_rendered_frames) in both precisions."""
    from dataclasses import asdict

    from detector.train import TrainConfig, train
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
