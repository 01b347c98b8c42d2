"""Can a small CNN place an object's eight corners from its own crop? A top-down yardstick for issue 25.

    .venv/bin/python benchmarks/crop_layout.py runs/validate/uov [--steps 1500] [--crop 64] [--jitter 1]
        [--head regress|integral]

The detector regresses every object's corners from the one feature vector at its anchor, at every
scale at once; on the CPU budget its corners land 0.41 of sqrt(box area) from the truth (median,
box-matched objects, docs/detector-training.md), where OKS 0.5 needs about 0.29 and OKS 0.75
about 0.19. Human-pose estimation answers the same question in two ways: bottom-up (one network,
as our detector) and top-down (crop each detected person, then a network that sees only that
crop), and top-down is the more precise at small budgets because every crop is seen at one scale.
This script measures what the top-down way would give here before the detector is changed: a
small CNN (the crop-heading stage's shape, detector/crop_stage.py) regresses the eight corners
of an object from a square crop about its 2D box, cut exactly as the detector's crop stage cuts
(`crop_boxes`), trained for a fixed number of steps from a fixed seed on the train split's
objects and scored on the test split's.

- The target of corner k is (x_k - c) / half for each axis: c the box centre and half the crop's
  half side (the box's longer side x (0.5 + margin)), so a corner at the crop's edge is +-1: the
  detector's crop units (crop_stage.to_crop_units).
- The boxes the crops are cut about are the true ones moved at random (`--jitter` scales the
  noise: centre by N(0, 0.06) of the box's width and height, each side by a log-normal factor of
  sigma 0.1), as a detector's boxes are; scored both on the true boxes and on moved ones, the
  predicted corners mapped back to the image with the box the crop was cut about.
- Horizontal flips (x negated, corners renumbered by conventions.FLIP_IDX) double the train set
  and average the prediction with its mirror image's (test-time flip).
- Scored as `omnigen eval` scores corners (detector/corner_errors.py): over the labelled corners
  (in the image, in front of the camera), the median distance relative to sqrt(true box area);
  `layout` forgives the 180-degree turn; `OKS>=.5` and `OKS>=.75` are the shares of objects whose
  own OKS (sigma 0.125, COCO's formula) reaches that threshold, what OKS mAP at those thresholds
  counts when the box is found. The box template (detector/box_template.py, fitted on the train
  split) placed on the same boxes is the baseline.
- `--head integral` swaps the regressor for a heatmap per corner read by its soft-argmax
  (`IntegralCorners`): whether pose estimation's way places the corners more precisely, measured
  before the crop stage changes.
- `--weights CKPT` scores a detector's crop stage (trained with it, `omnigen train --heading-crop`)
  on the same crops as a third row: whether the stage, trained on the detector's augmented
  windows beside everything else, places corners as well as the net trained here alone. A stage
  trained apart (`omnigen train-crop`'s checkpoint) is scored the same way.

Last line: `crop_layout (HEAD): rel X (template Y) on N test objects, jittered boxes rel A (template B);
OKS>=.5 C`; before it, with --weights, `crop_layout: the detector's crop stage (CKPT): rel X,
jittered boxes rel A; OKS>=.5 C`.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.heading_visibility import to_tensor  # noqa: E402
from omnigen.conventions import FLIP_IDX, NUM_KEYPOINTS, TURN_IDX, VIEWS  # noqa: E402
from omnigen.detector.boxes import box_area  # noqa: E402
from omnigen.detector.crop_stage import (CENTRE_JITTER, MARGIN, SIDE_JITTER, crop_boxes, from_crop_units,  # noqa: E402
                                         mirror_corners, outputs_of_crops, to_crop_units)
from omnigen.detector.heading import orient  # noqa: E402

OKS_K = 2 * 0.125  # COCO's kappa = 2 sigma, sigma the one omnigen.detector.oks_eval uses


@dataclass
class LayoutCrops:
    images: np.ndarray  # (N, S, S, 3) uint8, cut about `boxes`
    boxes: np.ndarray  # (N, 4) the xyxy box each crop was cut about (true or moved)
    true_boxes: np.ndarray  # (N, 4) the object's true 2D box
    keypoints: np.ndarray  # (N, 8, 2) true corners, NaN behind the camera
    labelled: np.ndarray  # (N, 8) bool: in the image and in front of the camera (what OKS scores)
    views: np.ndarray  # (N,) index into VIEWS
    classes: np.ndarray  # (N,) category names
    frames: np.ndarray  # (N,) the dataset index of the object's frame


def move_boxes(boxes: np.ndarray, rng: np.random.Generator, jitter: float) -> np.ndarray:
    """Boxes moved and resized as a detector's boxes miss the truth: the crop stage's training noise
    (crop_stage.jitter_boxes) scaled by `jitter`, drawn from a numpy generator."""
    if jitter <= 0:
        return boxes.copy()
    wh = boxes[:, 2:] - boxes[:, :2]
    centre = (boxes[:, :2] + boxes[:, 2:]) / 2 + rng.normal(0, CENTRE_JITTER * jitter, wh.shape) * wh
    wh = wh * np.exp(rng.normal(0, SIDE_JITTER * jitter, wh.shape))
    return np.concatenate([centre - wh / 2, centre + wh / 2], axis=1)


def collect(ds, frame_ids: list[str], crop: int, min_side: float, copies: int, jitter: float,
            rng: np.random.Generator, limit: int | None = None) -> LayoutCrops:
    """Crops of every object of the named frames whose box's longer side is at least min_side,
    `copies` of each, cut about boxes moved by `jitter` (0: the true box)."""
    from PIL import Image


    out: dict[str, list] = {k: [] for k in ("images", "boxes", "true_boxes", "keypoints", "labelled", "views", "classes", "frames")}
    n = 0
    for i in sorted(ds.index_of(f) for f in frame_ids):
        rec = ds[i]
        objs = [o for o in rec.objects
                if max(o.bbox[2] - o.bbox[0], o.bbox[3] - o.bbox[1]) >= min_side and np.isfinite(o.keypoints).any()]
        if not objs:
            continue
        image = torch.from_numpy(np.array(Image.open(ds.root / rec.image).convert("RGB"))).permute(2, 0, 1)
        true = np.repeat(np.stack([o.bbox for o in objs]).astype(np.float64), copies, axis=0)
        boxes = move_boxes(true, rng, jitter)
        crops = crop_boxes(image[None].float(), torch.zeros(len(boxes), dtype=torch.long),
                           torch.from_numpy(boxes).float(), crop, MARGIN)
        out["images"].append(crops.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy())
        out["boxes"].append(boxes)
        out["true_boxes"].append(true)
        out["keypoints"].append(np.repeat(np.stack([o.keypoints for o in objs]), copies, axis=0))
        out["labelled"].append(np.repeat(np.stack([o.in_image & ~o.behind_camera for o in objs]), copies, axis=0))
        out["views"].append(np.full(len(boxes), VIEWS.index(rec.view)))
        out["classes"].append(np.repeat(np.array([o.category for o in objs], dtype=object), copies))
        out["frames"].append(np.full(len(boxes), i))
        n += len(boxes)
        if limit and n >= limit:
            break
    if not n:
        raise SystemExit(f"crop_layout: {ds.root}: no object of at least {min_side} px in {len(frame_ids)} frames")
    return LayoutCrops(**{k: np.concatenate(v) for k, v in out.items()})


HEADS = ("regress", "integral")
"""How the benchmark's CNN gives the corners: `regress` (crop_stage.CropNet's way: the last feature
map flattened into 16 numbers) or `integral` (IntegralCorners: a heatmap per corner, read by its
soft-argmax)."""


def _block(cin: int, cout: int, pool: bool = True, dilation: int = 1) -> nn.Sequential:
    """Two 3x3 convolutions with batch norm and SiLU, then (where `pool`) a 2x2 max-pool."""
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=dilation, dilation=dilation, bias=False),
                         nn.BatchNorm2d(cout), nn.SiLU(),
                         nn.Conv2d(cout, cout, 3, padding=dilation, dilation=dilation, bias=False),
                         nn.BatchNorm2d(cout), nn.SiLU(), *([nn.MaxPool2d(2)] if pool else []))


def soft_argmax(heatmaps: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    """Heatmaps (N, K, s, s) -> (N, K, 2): each map's softmax-weighted mean of its cells' centres
    `centres` (s,), x then y. Differentiable (integral regression, Sun et al. 2018), so the corners
    are learned with the regressor's L1; the result stays within the centres' span."""
    n, k, s, _ = heatmaps.shape
    p = heatmaps.flatten(2).softmax(-1).view(n, k, s, s)
    return torch.stack([(p.sum(2) * centres).sum(-1), (p.sum(3) * centres).sum(-1)], -1)


class IntegralCorners(nn.Module):
    """(N, 3, S, S) -> (N, 16): a heatmap per corner at a quarter of the crop's side, read by its
    soft-argmax, in crop units (the crop's edges at +-1, cell centres at (j + 0.5) / s * 2 - 1).

    Why try it: pose estimation places keypoints more precisely from heatmaps than by regressing
    numbers from a flattened feature map, because each output cell keeps where it is in the
    image. Two pooled blocks (64 -> 16), then two at 16 x 16, the last dilated for context (its
    receptive field spans the crop: which corner is which depends on the whole object), and a 1x1
    convolution to the eight maps. A corner outside the crop is out of its reach (clamped to the
    edge); those lie beyond a moved box's crop and are rarely in the image."""

    def __init__(self, width: int = 16, crop: int = 64):
        super().__init__()
        if crop % 16:
            raise ValueError(f"IntegralCorners: crop side must be a multiple of 16, got {crop}")
        self.features = nn.Sequential(_block(3, width), _block(width, 2 * width),
                                      _block(2 * width, 4 * width, pool=False),
                                      _block(4 * width, 4 * width, pool=False, dilation=2))
        self.maps = nn.Conv2d(4 * width, NUM_KEYPOINTS, 1)
        s = crop // 4
        self.register_buffer("centres", (torch.arange(s, dtype=torch.float32) + 0.5) / s * 2 - 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return soft_argmax(self.maps(self.features(x)), self.centres).flatten(1)


def build_model(width: int = 16, crop: int = 64, head: str = "regress") -> nn.Module:
    """The benchmark's CNN: (N, 3, crop, crop) -> (N, 16), the corners in crop units. `regress`:
    crop_stage.CropNet's four blocks, the last feature map flattened (where a corner is, which a
    global average would throw away) into 16 outputs; `integral`: IntegralCorners."""
    if head == "integral":
        return IntegralCorners(width, crop)
    if head != "regress":
        raise ValueError(f"crop_layout: head {head!r} is not one of {', '.join(HEADS)}")
    side = crop // 16
    return nn.Sequential(_block(3, width), _block(width, 2 * width), _block(2 * width, 4 * width),
                         _block(4 * width, 4 * width), nn.Flatten(), nn.Linear(4 * width * side * side, 128), nn.SiLU(),
                         nn.Linear(128, 2 * NUM_KEYPOINTS))


def train(crops: LayoutCrops, steps: int, batch: int, seed: int, lr: float = 2e-3, head: str = "regress"):
    """A fixed-seed AdamW run with a one-cycle schedule; L1 on the corners in front of the camera;
    half of each batch mirrored."""

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = build_model(crop=crops.images.shape[1], head=head)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.1)
    x_all = to_tensor(crops.images)
    t_np = to_crop_units(torch.from_numpy(crops.keypoints), torch.from_numpy(crops.boxes)).numpy()
    valid_all = torch.from_numpy(np.isfinite(t_np).all(-1))
    t_all = torch.from_numpy(np.nan_to_num(t_np)).float()
    model.train()
    losses = []
    for _ in range(steps):
        idx = torch.from_numpy(rng.integers(0, len(t_all), batch))
        x, t, valid = x_all[idx].clone(), t_all[idx].clone(), valid_all[idx].clone()
        flip = torch.from_numpy(rng.random(batch) < 0.5)
        x[flip] = x[flip].flip(-1)
        t[flip] = mirror_corners(t[flip])
        valid[flip] = valid[flip][:, list(FLIP_IDX)]
        pred = model(x).view(-1, NUM_KEYPOINTS, 2)
        loss = ((pred - t).abs().sum(-1) * valid).sum() / valid.sum().clamp(min=1)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
    return model, losses


def predict(model, crops: LayoutCrops, batch: int = 256) -> np.ndarray:
    """(N, 8, 2) corners in image pixels, averaged with the mirrored crop's prediction."""

    model.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(crops.images), batch):
            x = to_tensor(crops.images[i:i + batch])
            p = model(x).view(-1, NUM_KEYPOINTS, 2)
            q = mirror_corners(model(x.flip(-1)).view(-1, NUM_KEYPOINTS, 2))
            out.append(((p + q) / 2).numpy())
    return from_crop_units(torch.from_numpy(np.concatenate(out).astype(np.float64)), torch.from_numpy(crops.boxes)).numpy()


def stage_corners(net, crops: LayoutCrops, batch: int = 256) -> np.ndarray:
    """(N, 8, 2) corners in image pixels that a trained detector's crop stage (crop_stage.CropNet)
    places on the same crops, as prediction does (crop_stage.refine): mirror-averaged, then turned
    where the stage's heading says the other face is the front."""
    net.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(crops.images), batch):
            boxes = torch.from_numpy(crops.boxes[i:i + batch]).float()
            h, t, _ = outputs_of_crops(net, to_tensor(crops.images[i:i + batch]), mirror=True)
            out.append(orient(from_crop_units(t, boxes), box_area(boxes), h).numpy())
    return np.concatenate(out).astype(np.float64)


def load_stage(weights: Path, crop: int):
    """The crop stage of a checkpoint trained with `--heading-crop` (its CropNet), on the CPU; a
    clear exit where it has none or crops at another side than `crop`."""
    from omnigen.detector.predict import load_for_prediction

    model, _ = load_for_prediction(weights, "cpu")
    net = model.crop_net
    if net is None:
        raise SystemExit(f"crop_layout: {weights}: has no crop stage (trained without --heading-crop)")
    if model.cfg.crop_position:
        raise SystemExit(f"crop_layout: {weights}: its crop stage is told where each crop was cut (train-crop "
                         "--position), which these crops do not record; score it with benchmarks/crop_apart.py or "
                         "compare_checkpoints.py")
    if model.cfg.heading_crop != crop:
        raise SystemExit(f"crop_layout: {weights}: its crop stage cuts {model.cfg.heading_crop}-pixel crops; "
                         f"pass --crop {model.cfg.heading_crop}")
    return net.float()


def template_corners(template, crops: LayoutCrops) -> np.ndarray:
    """The box template's corners on the boxes the crops were cut about."""
    wh = crops.boxes[:, 2:] - crops.boxes[:, :2]
    centre = (crops.boxes[:, :2] + crops.boxes[:, 2:]) / 2
    layouts = np.stack([template.layout(str(c), VIEWS[v]) for c, v in zip(crops.classes, crops.views)])
    return layouts * wh[:, None] + centre[:, None]


@dataclass
class Score:
    rel: float  # median corner error / sqrt(true box area), labelled corners
    layout_rel: float  # the same with the 180-degree turn forgiven per object
    oks50: float  # share of objects with OKS >= 0.5
    oks75: float
    objects: int


def score(pred: np.ndarray, crops: LayoutCrops, mask: np.ndarray | None = None) -> Score:
    m = np.ones(len(pred), bool) if mask is None else mask
    lab = crops.labelled[m] & np.isfinite(crops.keypoints[m]).all(-1)
    keep = lab.any(1)
    lab, gt, p = lab[keep], crops.keypoints[m][keep], pred[m][keep]
    if not len(gt):
        return Score(float("nan"), float("nan"), float("nan"), float("nan"), 0)
    wh = crops.true_boxes[m][keep, 2:] - crops.true_boxes[m][keep, :2]
    area = np.maximum(wh.prod(1), 1e-9)
    d = np.linalg.norm(np.nan_to_num(p - gt), axis=-1)  # (n, 8)
    d_turn = np.linalg.norm(np.nan_to_num(p[:, list(TURN_IDX)] - gt), axis=-1)
    rel = d / np.sqrt(area)[:, None]
    mean_d = (d * lab).sum(1) / lab.sum(1)
    mean_turn = (d_turn * lab).sum(1) / lab.sum(1)
    layout = np.where((mean_turn < mean_d)[:, None], d_turn, d) / np.sqrt(area)[:, None]
    oks = (np.exp(-d ** 2 / (2 * area[:, None] * OKS_K ** 2)) * lab).sum(1) / lab.sum(1)
    return Score(float(np.median(rel[lab])), float(np.median(layout[lab])), float(np.mean(oks >= 0.5)),
                 float(np.mean(oks >= 0.75)), int(len(gt)))


def open_splits(dataset: Path, script: str):
    """(the opened dataset, its train frame ids, its test frame ids); a clear exit naming the
    dataset where either split is missing."""
    from omnigen.dataset import Dataset
    from omnigen.splits import read_split

    try:
        train_ids, test_ids = read_split(dataset, "train"), read_split(dataset, "test")
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{script}: {dataset}: needs splits/train.txt and splits/test.txt ({exc})")
    return Dataset.open(dataset), train_ids, test_ids


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", type=Path, help="a merged UrbanOmniView dataset with train and test splits")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--crop", type=int, default=64, help="crop side in pixels (a multiple of 16)")
    ap.add_argument("--min-side", type=float, default=4.0, help="smallest longer box side kept, px (the crop stage's)")
    ap.add_argument("--jitter", type=float, default=1.0, help="scale of the box noise (0: crops about the true boxes)")
    ap.add_argument("--copies", type=int, default=2, help="crops per train object, each about its own moved box")
    ap.add_argument("--limit", type=int, default=None, help="at most this many train crops (a quick look)")
    ap.add_argument("--head", default="regress", choices=HEADS,
                    help="how the CNN gives the corners: regressed from its flattened features (the crop stage's) "
                         "or read from a heatmap each (integral)")
    ap.add_argument("--weights", type=Path, default=None,
                    help="also score this checkpoint's crop stage (trained with the detector, --heading-crop) "
                         "on the same crops")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    a = ap.parse_args(argv)
    if a.crop % 16:
        raise SystemExit(f"crop_layout: --crop {a.crop}: must be a multiple of 16 (four 2x2 pools)")

    from omnigen.detector.box_template import fit_box_template
    from omnigen.progress import print_table

    if a.threads:
        torch.set_num_threads(a.threads)
    t0 = time.perf_counter()
    ds, train_ids, test_ids = open_splits(a.dataset, "crop_layout")
    rng = np.random.default_rng(a.seed)
    tr = collect(ds, train_ids, a.crop, a.min_side, a.copies, a.jitter, rng, a.limit)
    te_true = collect(ds, test_ids, a.crop, a.min_side, 1, 0.0, rng)
    te_moved = collect(ds, test_ids, a.crop, a.min_side, 1, max(a.jitter, 1.0), rng)
    print(f"crops: train {len(tr.images)} ({a.copies} a object), test {len(te_true.images)} "
          f"({time.perf_counter() - t0:.1f} s)", flush=True)
    template = fit_box_template(ds, train_ids, fitted_from="train")
    stage = load_stage(a.weights, a.crop) if a.weights else None
    t1 = time.perf_counter()
    model, losses = train(tr, a.steps, a.batch, a.seed, head=a.head)
    print(f"trained {a.steps} steps in {time.perf_counter() - t1:.1f} s; L1 first 50 {np.mean(losses[:50]):.3f}, "
          f"last 50 {np.mean(losses[-50:]):.3f}", flush=True)

    rows, last = [], {}
    for boxes_name, te in (("true", te_true), ("moved", te_moved)):
        preds = {"crop net": predict(model, te), "box template": template_corners(template, te)}
        if stage is not None:
            preds["detector's stage"] = stage_corners(stage, te)
        for who, pred in preds.items():
            groups = [("all", None)] + [(f"view={v}", te.views == VIEWS.index(v)) for v in VIEWS
                                        if np.any(te.views == VIEWS.index(v))]
            for group, mask in groups:
                s = score(pred, te, mask)
                rows.append([boxes_name, who, group, str(s.objects), f"{s.rel:.3f}", f"{s.layout_rel:.3f}",
                             f"{s.oks50:.3f}", f"{s.oks75:.3f}"])
                if mask is None:
                    last[(boxes_name, who)] = s
    print_table("corners from the object's own crop, test objects",
                ["boxes", "corners by", "group", "objects", "rel", "layout", "OKS>=.5", "OKS>=.75"], rows)
    c, t = last[("true", "crop net")], last[("true", "box template")]
    cm, tm = last[("moved", "crop net")], last[("moved", "box template")]
    if stage is not None:
        d, dm = last[("true", "detector's stage")], last[("moved", "detector's stage")]
        print(f"crop_layout: the detector's crop stage ({a.weights}): rel {d.rel:.3f}, jittered boxes rel "
              f"{dm.rel:.3f}; OKS>=.5 {dm.oks50:.3f}")
    print(f"crop_layout ({a.head}): rel {c.rel:.3f} (template {t.rel:.3f}) on {c.objects} test objects, jittered boxes rel "
          f"{cm.rel:.3f} (template {tm.rel:.3f}); OKS>=.5 {cm.oks50:.3f} (template {tm.oks50:.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
