"""Does the crop stage name rare classes better when its crops are drawn class-balanced?

    .venv/bin/python benchmarks/crop_classes.py runs/validate/uov [--steps 1500] [--draws uniform balanced]

The crop stage (detector/crop_stage.py, `train --crop-classes`) rescores each detection of class c
by its crop's softmax p_c. The evaluation's mAP is the mean of per-class APs, and a class's AP
depends only on how its own detections rank against each other (a constant factor on one class's
scores changes nothing), so what the crop adds to a class is how well p_c separates that class's
objects from the others' (trucks, vans, everything the head also calls a bus). make validate's run
of 2026-11-27 named 3 of 111 found objects of the seven rarest classes right
(benchmarks/class_confusion.py): its crops were drawn uniformly from a batch's labelled objects,
about 16 cars to every van and hundreds to every tricycle.

This script trains the crop stage's network (`CropNet` with classes, cross-entropy only) the way
the detector's training feeds it, once per draw, from one seed:

- a step is a batch of `--batch-frames` training frames drawn with make validate's repeat factors
  (detector/balance.py, `--repeat-thresh`); its candidates are the frames' objects of at least
  MIN_SIDE pixels, each cut about its box moved as a detector's boxes miss the truth (`--copies`
  moved boxes an object, drawn once; crop_layout.collect);
- of those, MAX_CROPS are drawn by `crop_stage.draw_rows`: `uniform` (the stage's draw before
  this benchmark) or `balanced` (each candidate weighted by 1 / its class's candidates in the
  batch); half of them mirrored.

Scored on every test object's crop about a moved box (mirror-averaged, as prediction does): per
class, the one-vs-rest average precision of p_c over all test crops (`AP`, what ranks a class's
detections) and the share of the class's crops whose most probable class is theirs (`named`).
`mean AP` is over the classes the test split holds, as mAP is.

Last line: `crop_classes: mean AP <draw> X, <draw> Y, ...; rare-class named <draw> A, ...`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.crop_layout import LayoutCrops, collect, open_splits  # noqa: E402
from benchmarks.heading_visibility import to_tensor  # noqa: E402

DRAWS = ("uniform", "balanced")
RARE = 200
"""A class with fewer training objects than this counts as rare in the last line's `named` share."""


def one_vs_rest_ap(scores: np.ndarray, positive: np.ndarray) -> float:
    """Average precision of ranking `positive` items first by `scores` (the area under the
    precision-recall steps, precision taken at each positive); NaN without positives."""
    n_pos = int(positive.sum())
    if not n_pos:
        return float("nan")
    order = np.argsort(-scores, kind="stable")
    hits = positive[order].astype(np.float64)
    precision = np.cumsum(hits) / np.arange(1, len(hits) + 1)
    return float((precision * hits).sum() / n_pos)


def frame_batches(frames: np.ndarray, weights: np.ndarray, batch: int, steps: int, rng: np.random.Generator
                  ) -> list[np.ndarray]:
    """`steps` batches of `batch` distinct frame indices, each drawn with probability ~ weights."""
    p = weights / weights.sum()
    return [rng.choice(len(frames), size=min(batch, len(frames)), replace=False, p=p) for _ in range(steps)]


def train(crops: LayoutCrops, labels: np.ndarray, frames: np.ndarray, batches: list[np.ndarray], nc: int,
          draw: str, seed: int, lr: float = 2e-3):
    """CropNet with `nc` class logits trained by cross-entropy on MAX_CROPS candidates a step."""
    import torch
    import torch.nn.functional as F

    from omnigen.detector.crop_stage import MAX_CROPS, CropNet, draw_rows, split_outputs

    torch.manual_seed(seed)
    net = CropNet(crops.images.shape[1], num_classes=nc)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=len(batches), pct_start=0.1)
    x_all, y_all = to_tensor(crops.images), torch.from_numpy(labels)
    by_frame = {f: np.flatnonzero(crops.frames == f) for f in np.unique(crops.frames)}
    net.train()
    losses = []
    for step_frames in batches:
        cand = np.concatenate([by_frame[int(frames[f])] for f in step_frames])  # a frame here has crops
        cand_t = torch.from_numpy(cand)
        idx = draw_rows(cand_t, MAX_CROPS, y_all[cand_t] if draw == "balanced" else None)
        x, y = x_all[idx].clone(), y_all[idx]
        flip = torch.rand(len(idx)) < 0.5
        x[flip] = x[flip].flip(-1)
        _, _, logits = split_outputs(net(x))
        loss = F.cross_entropy(logits, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
    return net, losses


def probabilities(net, crops: LayoutCrops, batch: int = 256) -> np.ndarray:
    """(N, nc) softmax of the mirror-averaged logits, as prediction rescores by (crop_stage.refine)."""
    import torch

    from omnigen.detector.crop_stage import split_outputs

    net.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(crops.images), batch):
            x = to_tensor(crops.images[i:i + batch])
            a, b = split_outputs(net(x))[2], split_outputs(net(x.flip(-1)))[2]
            out.append(((a + b) / 2).softmax(-1).numpy())
    return np.concatenate(out)


def labelled(crops: LayoutCrops, taxonomy) -> tuple[LayoutCrops, np.ndarray]:
    """The crops of the classes `taxonomy` keeps, and their class ids."""
    ids = np.array([-1 if (c := taxonomy.class_id(str(name))) is None else c for name in crops.classes], dtype=np.int64)
    keep = ids >= 0
    return LayoutCrops(**{k: v[keep] for k, v in vars(crops).items()}), ids[keep]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", type=Path, help="a merged UrbanOmniView dataset with train and test splits")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch-frames", type=int, default=16, help="frames a step (make validate's --batch)")
    ap.add_argument("--crop", type=int, default=64, help="crop side (make validate's --heading-crop)")
    ap.add_argument("--copies", type=int, default=2, help="moved boxes an object, drawn once")
    ap.add_argument("--repeat-thresh", type=float, default=0.3, help="frames' repeat factors (train --repeat-thresh)")
    ap.add_argument("--draws", nargs="+", default=list(DRAWS), choices=DRAWS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    a = ap.parse_args(argv)
    if a.crop % 16:
        raise SystemExit(f"crop_classes: --crop {a.crop}: must be a multiple of 16 (four 2x2 pools)")

    import torch

    from omnigen.detector.balance import repeat_factors
    from omnigen.detector.crop_stage import MIN_SIDE
    from omnigen.progress import print_table
    from omnigen.taxonomy import load_taxonomy

    if a.threads:
        torch.set_num_threads(a.threads)
    t0 = time.perf_counter()
    ds, train_ids, test_ids = open_splits(a.dataset, "crop_classes")
    taxonomy = load_taxonomy("fine")  # what make validate trains on
    classes = taxonomy.classes
    rng = np.random.default_rng(a.seed)
    tr, y_tr = labelled(collect(ds, train_ids, a.crop, MIN_SIDE, a.copies, 1.0, rng), taxonomy)
    te, y_te = labelled(collect(ds, test_ids, a.crop, MIN_SIDE, 1, 1.0, rng), taxonomy)
    frames = np.unique(tr.frames)
    frame_classes = [y_tr[tr.frames == f] for f in frames]
    batches = frame_batches(frames, repeat_factors(frame_classes, len(classes), a.repeat_thresh), a.batch_frames,
                            a.steps, np.random.default_rng(a.seed + 1))
    train_count = np.bincount(y_tr, minlength=len(classes)) // a.copies
    print(f"crops: train {len(tr.images)} ({a.copies} a object, {len(frames)} frames), test {len(te.images)} "
          f"({time.perf_counter() - t0:.1f} s)", flush=True)

    ap_by, named_by = {}, {}
    for draw in a.draws:
        t1 = time.perf_counter()
        net, losses = train(tr, y_tr, frames, batches, len(classes), draw, a.seed)
        p = probabilities(net, te)
        ap_by[draw] = np.array([one_vs_rest_ap(p[:, c], y_te == c) for c in range(len(classes))])
        named_by[draw] = np.array([np.mean(p[y_te == c].argmax(1) == c) if np.any(y_te == c) else np.nan
                                   for c in range(len(classes))])
        print(f"{draw}: {len(losses)} steps in {time.perf_counter() - t1:.1f} s; cross-entropy first 50 "
              f"{np.mean(losses[:50]):.3f}, last 50 {np.mean(losses[-50:]):.3f}", flush=True)

    rows = []
    for c, name in enumerate(classes):
        n_te = int(np.sum(y_te == c))
        if not n_te:
            continue
        rows.append([name, str(int(train_count[c])), str(n_te)]
                    + [f"{ap_by[d][c]:.3f} / {named_by[d][c]:.2f}" for d in a.draws])
    print_table("crop classifier on moved test boxes: one-vs-rest AP / share named right",
                ["class", "train objects", "test crops"] + list(a.draws), rows)
    held = np.array([np.any(y_te == c) for c in range(len(classes))])
    rare = held & (train_count < RARE)
    means = ", ".join(f"{d} {np.nanmean(ap_by[d][held]):.3f}" for d in a.draws)
    named = ", ".join(f"{d} {np.nanmean(named_by[d][rare]):.2f}" for d in a.draws)
    print(f"crop_classes: mean AP {means}; rare-class named {named} ({int(rare.sum())} classes under {RARE} "
          f"train objects)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
