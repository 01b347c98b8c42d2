"""Whether a turn-aware checkpoint's own choice of corner order follows the true heading.

    .venv/bin/python benchmarks/turn_targets.py runs/learning/RUN/last.pt [--batches 6]

A `--kpt-turn` model regresses corners up to the 180-degree turn and learns the turn as a class
(detector/loss.py, `turn_targets`). Its targets are relative to what the branch predicts: where
the branch's own choice of order is the labelled one, the target is "not turned". This script
runs the checkpoint (its EMA weights) over training crops drawn as training draws them and
prints, per batch and overall, the share of positive (anchor, object) pairs whose target is
"turned" and the turn loss. A share near 0.5 with a loss near log 2 = 0.693 says the branch's
order is unrelated to the heading and the turn class has nothing it can learn from yet; a share
near 0 says the branch follows the labelled order (docs/detector-training.md).

Last line: `turn targets: turned S of N positives, turn loss L`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--batches", type=int, default=6)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seed", type=int, default=1, help="augmentation seed of the crops (not the run's)")
    args = ap.parse_args(argv)

    import torch

    import omnigen.detector.loss as loss_module
    from omnigen.detector.checkpoint import checkpoint_taxonomy, load_model
    from omnigen.detector.data import Augment, KeypointDataset, collate, split_frames
    from omnigen.detector.loss import DetectionLoss, LossGains
    from omnigen.detector.train import TrainConfig

    model, state = load_model(args.checkpoint)
    if not model.cfg.kpt_turn:
        raise SystemExit(f"turn_targets: {args.checkpoint} is not a turn-aware model (train --kpt-turn)")
    cfg = TrainConfig(**{"optimizer": "adam", **state["train_config"]})
    data = KeypointDataset(cfg.dataset, checkpoint_taxonomy(state), cfg.imgsz, split_frames(cfg.dataset, cfg.train_split),
                           Augment(**cfg.augment), cfg.out_of_image, args.seed, crop=cfg.crop)
    criterion = DetectionLoss(model.cfg.num_classes, gains=LossGains(kpt_l1=cfg.kpt_l1))
    seen: list[torch.Tensor] = []
    original = loss_module.turn_targets

    def recording(*a):  # the loss's own targets, as training computes them
        t = original(*a)
        seen.append(t)
        return t

    loss_module.turn_targets = recording
    turned = total = 0
    losses = []
    try:
        model.train()  # the training-mode head output, which the loss takes
        with torch.no_grad():
            for b in range(args.batches):
                lo = (b * args.batch) % max(len(data), 1)
                images, targets, _ = collate([data[(lo + i) % len(data)] for i in range(args.batch)])
                images = images.float().div(255) if not images.is_floating_point() else images
                _, parts = criterion(model(images), targets)
                t = seen[-1]
                turned, total = turned + int(t.sum()), total + len(t)
                losses.append(float(parts["turn"]))
                share = float(t.float().mean()) if len(t) else float("nan")
                print(f"batch {b}: {len(t)} positives, turned {share:.2f}, turn loss {losses[-1]:.3f}")
    finally:
        loss_module.turn_targets = original
    mean_loss = sum(losses) / len(losses) if losses else float("nan")
    print(f"turn targets: turned {turned / max(total, 1):.2f} of {total} positives, turn loss {mean_loss:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
