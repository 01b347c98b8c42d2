"""What the crop-heading stage costs: seconds per training step and per predicted image, by crop side.

A model with a crop stage (the recipe's `crop_stage.side=S`, detector/model/crop_stage.py) runs a small
CNN on up to MAX_CROPS labelled boxes every training step and, after NMS, on each image's
MAX_REFINE best detections and their mirror images. That CNN works on S x S crops at full
resolution in its first block, which on a CPU costs far more than its size suggests (few channels,
large feature maps: memory bound). This script times, in one run with the configurations
alternating round by round so that a busy machine slows all alike:

- a whole training step as `omnigen train` runs it (detector/train_step.TrainStep: forward with the
  crops, loss, backward, clipping, AdamW, EMA; bf16 autocast where the CPU runs it natively), for
  nano P2 without the stage and with each crop side, on a batch of fake frames with 8 objects each
  (16 x 8 = 128 labelled boxes: the stage's cap), or with `--dataset` on the first batch of a real
  dataset's train split as training draws it (augmented, `--imgsz` windows of 640-pixel inputs);
- the stage at prediction: `refine_detections` on one 640 x 640 image with 300 and with 100
  detections (each cropped and mirrored), per crop side.

Prints medians and each configuration's step time as a ratio of the stage-free step's.

    .venv/bin/python benchmarks/bench_crop_stage.py [--sides 32 64] [--rounds 8] [--threads 2] [--dataset runs/validate/uov]
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

from omnigen.detector.data.samples import Augment, KeypointDataset  # noqa: E402
from omnigen.detector.training.ema import ModelEMA  # noqa: E402
from omnigen.detector.model.crop_stage import MAX_CROPS, refine_detections  # noqa: E402
from omnigen.detector.training.loss import DetectionLoss  # noqa: E402
from omnigen.detector.model.network import DetectorConfig, KeypointDetector  # noqa: E402
from omnigen.detector.model.outputs import Detections  # noqa: E402
from omnigen.detector.training.train import TrainConfig, autocast_dtype, make_optimizer  # noqa: E402
from omnigen.detector.data.loader import collate_uint8  # noqa: E402
from omnigen.detector.training.step import TrainStep, to_device  # noqa: E402
from omnigen.fakes import write_fake_dataset  # noqa: E402
from omnigen.taxonomy import load_taxonomy  # noqa: E402


def train_step(side: int, images: torch.Tensor, targets: dict, amp: torch.dtype | None, nc: int):
    """A TrainStep of nano P2 with crop side `side` (0: no stage), fixed seed."""
    torch.manual_seed(0)
    model = KeypointDetector(DetectorConfig("n", p2=True, num_classes=nc, kpt_mode="box", kpt_heading=True,
                                            heading_crop=side)).train()
    cfg = TrainConfig(dataset=".", out=".", optimizer="adamw", lr0=2e-3)
    optimizer = make_optimizer(cfg, model)
    step = TrainStep(model, model, DetectionLoss(nc), optimizer, torch.amp.GradScaler("cpu", enabled=False),
                     ModelEMA(model, cfg.ema_decay, cfg.ema_tau), amp)
    return lambda: step(images, targets), model


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sides", type=int, nargs="+", default=[32, 64], help="crop sides to time (multiples of 16)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--imgsz", type=int, default=320, help="training input (the recipe's data.window, make validate's)")
    ap.add_argument("--rounds", type=int, default=8, help="timed rounds; each runs every configuration once")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--dataset", type=Path, default=None,
                    help="time on a batch of this dataset's train split (640-pixel inputs, --imgsz windows)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    device = torch.device("cpu")
    amp = autocast_dtype("auto" if device.type != "cpu" else "bf16", device)
    taxonomy = load_taxonomy("fine")
    nc = len(taxonomy.classes)
    if a.dataset is not None:
        from omnigen.splits import read_split

        data = KeypointDataset(a.dataset, taxonomy, 640, read_split(a.dataset, "train"), Augment(), crop=a.imgsz)
        images, targets, _ = collate_uint8([data[i] for i in range(a.batch)])
    else:
        with tempfile.TemporaryDirectory() as tmp:
            write_fake_dataset(tmp, a.batch, objects_per_frame=8, seed=0)
            data = KeypointDataset(tmp, taxonomy, a.imgsz, None, Augment())
            images, targets, _ = collate_uint8([data[i] for i in range(a.batch)])
    images, targets = to_device(images, targets, device, False)

    runs, models = {}, {}
    for side in [0] + a.sides:
        runs[f"train step, side {side or '-'}"], models[side] = train_step(side, images, targets, amp, nc)
    image = torch.rand(1, 3, 640, 640, generator=torch.Generator().manual_seed(0))
    g = torch.Generator().manual_seed(1)
    xy = torch.rand(300, 2, generator=g) * 560
    wh = 8 + torch.rand(300, 2, generator=g) * 72
    dets = Detections(torch.cat([xy, xy + wh], 1), torch.linspace(1, 0, 300), torch.zeros(300, dtype=torch.long),
                      torch.rand(300, 8, 3, generator=g) * 640)
    for side in a.sides:
        net = models[side].crop_net.eval()
        for k in (300, 100):
            def refine(net=net, side=side, k=k):
                with torch.no_grad(), torch.autocast("cpu", dtype=amp or torch.float32, enabled=amp is not None):
                    refine_detections(net, side, image, [dets], max_refine=k)
            runs[f"refine {k} dets, side {side}"] = refine
    for fn in runs.values():  # warm-up: oneDNN picks its kernels on the first calls
        fn()
    times: dict[str, list[float]] = {k: [] for k in runs}
    for _ in range(a.rounds):
        for name, fn in runs.items():
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    med = {k: statistics.median(v) for k, v in times.items()}
    base = med["train step, side -"]
    labelled = int(targets["bboxes"].shape[0])
    print(f"crop stage cost: nano P2, batch {a.batch} at {a.imgsz} px ({a.dataset or 'fake frames'}), {labelled} labelled boxes "
          f"(at most {MAX_CROPS} cropped), {a.threads} threads, autocast {amp}; median of {a.rounds} rounds")
    print("| what | s | / stage-free step |")
    print("|---|---|---|")
    for name, t in med.items():
        print(f"| {name} | {t:.3f} | {t / base:.2f} |")
    sides = ", ".join(f"side {s} {med[f'train step, side {s}'] / base:.2f}x, refine 300 {med[f'refine 300 dets, side {s}']:.2f} s"
                      for s in a.sides)
    print(f"crop_stage: stage-free step {base:.3f} s; {sides}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
