"""Can an object's front be told from its back in these images? A crop classifier answers.

    .venv/bin/python benchmarks/heading_visibility.py runs/validate2/uov [--steps 1500] [--crop 64]

Issue 25's detector learns where an object's corners are but not which face is the front: about
half its matched objects come out turned 180 degrees, and its turn logit stays at chance. That is
either a learning problem (too few steps, a loss that gives no signal) or a data problem (the
rendered vehicles carry no front/back cue a network can see at their image size). This script
separates the two with the smallest model that could see such a cue: a small CNN on square crops
of single vehicles, trained for a fixed number of steps from a fixed seed on the train split and
scored on the test split.

The label is chosen so that the cuboid alone cannot give it away. An object turned 180 degrees
about its vertical axis projects to the same eight points with front and rear swapped
(conventions.TURN_IDX), so its silhouette is the same; only appearance (hood against boot, lights,
where the cabin sits) tells the two apart. For a vehicle seen from the side the label is whether
its front face's image centre lies to the right of its rear face's (`facing_right`); objects whose
faces are within --min-offset of a box width of each other (seen from the front or rear) carry no
such label and are left out. Horizontal flips with the label flipped double the train set (the
mirror image of a vehicle is a vehicle facing the other way).

Prints balanced accuracy (chance 0.5 whatever the classes' shares) on the test crops overall, per view and per size; the last line:
`heading_visibility: accuracy X on N test crops (chance 0.5; train N), ego A, infrastructure B, aerial C`.
Accuracy near 0.5 says the renders hold no usable cue at that size; well above it says they do and
the detector's training is what must change.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.conventions import FRONT_CORNERS as FRONT, REAR_CORNERS as REAR, VIEWS  # noqa: E402

# classes with a front and a rear that differ in shape (people and cones do not)
VEHICLES = ("car", "van", "truck", "bus", "tram", "cyclist", "motorcyclist", "tricyclist")
SIZE_BUCKETS = ((0, 48, "24-48 px"), (48, 96, "48-96 px"), (96, 10**9, ">= 96 px"))


def facing_right(keypoints: np.ndarray, bbox: np.ndarray, min_offset: float) -> bool | None:
    """Whether the front face's image centre is right of the rear face's; None when the two are
    within min_offset box widths of each other (a front or rear view, no left/right to tell)."""
    front = np.nanmean(keypoints[list(FRONT), 0])
    rear = np.nanmean(keypoints[list(REAR), 0])
    width = float(bbox[2] - bbox[0])
    if not np.isfinite(front - rear) or width <= 0 or abs(front - rear) < min_offset * width:
        return None
    return bool(front > rear)


def square_crop(image: np.ndarray, bbox: np.ndarray, size: int, margin: float = 0.1) -> np.ndarray:
    """The bbox grown by margin on each side and squared about its centre, cut out of the image
    (zero outside it) and resized to size x size; (size, size, 3) uint8."""
    from PIL import Image

    x1, y1, x2, y2 = (float(v) for v in bbox)
    cx, cy = (x1 + x2) / 2, (y1 + y2) / 2
    half = max(x2 - x1, y2 - y1) * (0.5 + margin)
    a, b = int(np.floor(cx - half)), int(np.floor(cy - half))
    side = max(1, int(np.ceil(2 * half)))
    h, w = image.shape[:2]
    canvas = np.zeros((side, side, 3), dtype=np.uint8)
    sx1, sy1, sx2, sy2 = max(a, 0), max(b, 0), min(a + side, w), min(b + side, h)
    if sx2 > sx1 and sy2 > sy1:
        canvas[sy1 - b:sy2 - b, sx1 - a:sx2 - a] = image[sy1:sy2, sx1:sx2, :3]
    return np.asarray(Image.fromarray(canvas).resize((size, size), Image.BILINEAR))


@dataclass
class Crops:
    images: np.ndarray  # (N, S, S, 3) uint8
    labels: np.ndarray  # (N,) 1 where facing right
    views: np.ndarray  # (N,) index into VIEWS
    sides: np.ndarray  # (N,) the bbox's longer side, px


def collect(ds, frame_ids: list[str], crop: int, min_side: float, min_offset: float,
            max_occlusion: int, limit: int | None = None) -> Crops:
    """Every labelled vehicle of the named frames of dataset `ds` that is large and unoccluded enough."""
    from PIL import Image

    root = ds.root
    images, labels, views, sides = [], [], [], []
    for i in sorted(ds.index_of(f) for f in frame_ids):  # in the dataset's order, whatever the split file's
        rec = ds[i]
        picked = []
        for obj in rec.objects:
            side = float(max(obj.bbox[2] - obj.bbox[0], obj.bbox[3] - obj.bbox[1]))
            if (obj.category not in VEHICLES or min(obj.bbox[2] - obj.bbox[0], obj.bbox[3] - obj.bbox[1]) < min_side
                    or obj.truncation > 0.3 or not (0 <= obj.occlusion_level <= max_occlusion)):
                continue
            label = facing_right(obj.keypoints, obj.bbox, min_offset)
            if label is not None:
                picked.append((obj, label, side))
        if not picked:
            continue
        image = np.asarray(Image.open(root / rec.image).convert("RGB"))
        for obj, label, side in picked:
            images.append(square_crop(image, obj.bbox, crop))
            labels.append(int(label))
            views.append(VIEWS.index(rec.view))
            sides.append(side)
        if limit and len(labels) >= limit:
            break
    if not labels:
        return Crops(np.zeros((0, crop, crop, 3), np.uint8), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    return Crops(np.stack(images), np.array(labels), np.array(views), np.array(sides))


def build_model(width: int = 16):
    import torch.nn as nn

    def block(cin, cout):
        return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.SiLU(),
                             nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.SiLU(),
                             nn.MaxPool2d(2))

    return nn.Sequential(block(3, width), block(width, 2 * width), block(2 * width, 4 * width),
                         block(4 * width, 4 * width), nn.AdaptiveAvgPool2d(1), nn.Flatten(),
                         nn.Linear(4 * width, 1))


def to_tensor(images: np.ndarray):
    import torch

    return torch.from_numpy(images).permute(0, 3, 1, 2).float().div_(255.0)


def train(crops: Crops, steps: int, batch: int, seed: int, lr: float = 2e-3):
    """A fixed-seed AdamW run with a cosine schedule; each batch half flipped (labels flipped too)."""
    import torch

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = build_model()
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.1)
    loss_fn = torch.nn.BCEWithLogitsLoss()
    x_all, y_all = to_tensor(crops.images), torch.from_numpy(crops.labels).float()
    model.train()
    losses = []
    for _ in range(steps):
        idx = torch.from_numpy(rng.integers(0, len(y_all), batch))
        x, y = x_all[idx].clone(), y_all[idx].clone()
        flip = torch.from_numpy(rng.random(batch) < 0.5)
        x[flip] = x[flip].flip(-1)
        y[flip] = 1.0 - y[flip]
        loss = loss_fn(model(x).squeeze(1), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
    return model, losses


def predict(model, crops: Crops, batch: int = 256) -> np.ndarray:
    """Probability of facing right, averaged with the flipped crop's (test-time flip)."""
    import torch

    model.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(crops.labels), batch):
            x = to_tensor(crops.images[i:i + batch])
            p = torch.sigmoid(model(x).squeeze(1))
            q = 1.0 - torch.sigmoid(model(x.flip(-1)).squeeze(1))
            out.append(((p + q) / 2).numpy())
    return np.concatenate(out) if out else np.zeros(0)


def accuracy(prob: np.ndarray, labels: np.ndarray) -> float:
    """Balanced accuracy: the mean of the two classes' recalls, so that chance is 0.5 however many
    of the crops face right (a street's vehicles mostly face one way in a given view)."""
    recalls = [float(np.mean((prob[labels == c] > 0.5) == bool(c))) for c in (0, 1) if np.any(labels == c)]
    return float(np.mean(recalls)) if recalls else float("nan")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", type=Path, help="a merged UrbanOmniView dataset with train and test splits")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--crop", type=int, default=64, help="crop side in pixels")
    ap.add_argument("--min-side", type=float, default=24.0, help="smallest bbox side kept, px")
    ap.add_argument("--min-offset", type=float, default=0.25,
                    help="front and rear centres closer than this share of the box width carry no label")
    ap.add_argument("--max-occlusion", type=int, default=1, help="largest occlusion level kept (0-3)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    a = ap.parse_args(argv)

    import torch

    from omnigen.splits import read_split

    if a.threads:
        torch.set_num_threads(a.threads)
    t0 = time.perf_counter()
    try:
        train_ids, test_ids = read_split(a.dataset, "train"), read_split(a.dataset, "test")
    except (OSError, ValueError) as exc:
        raise SystemExit(f"heading_visibility: {a.dataset}: needs splits/train.txt and splits/test.txt ({exc})")
    from omnigen.dataset import Dataset

    ds = Dataset.open(a.dataset)  # once, for both splits
    kw = dict(crop=a.crop, min_side=a.min_side, min_offset=a.min_offset, max_occlusion=a.max_occlusion)
    tr, te = collect(ds, train_ids, **kw), collect(ds, test_ids, **kw)
    if len(tr.labels) < a.batch or not len(te.labels):
        raise SystemExit(f"heading_visibility: {a.dataset}: too few labelled crops (train {len(tr.labels)}, "
                         f"test {len(te.labels)}); lower --min-side or --min-offset")
    print(f"crops: train {len(tr.labels)} ({tr.labels.mean():.2f} facing right), test {len(te.labels)} "
          f"({time.perf_counter() - t0:.1f} s)", flush=True)
    t1 = time.perf_counter()
    model, losses = train(tr, a.steps, a.batch, a.seed)
    print(f"trained {a.steps} steps in {time.perf_counter() - t1:.1f} s; loss first 50 {np.mean(losses[:50]):.3f}, "
          f"last 50 {np.mean(losses[-50:]):.3f}", flush=True)
    prob_te, prob_tr = predict(model, te), predict(model, tr)

    from omnigen.progress import print_table

    rows = [["all", str(len(te.labels)), f"{accuracy(prob_te, te.labels):.3f}"]]
    for v, name in enumerate(VIEWS):
        m = te.views == v
        rows.append([f"view={name}", str(int(m.sum())), f"{accuracy(prob_te[m], te.labels[m]):.3f}" if m.any() else "-"])
    for lo, hi, name in SIZE_BUCKETS:
        m = (te.sides >= lo) & (te.sides < hi)
        rows.append([f"size {name}", str(int(m.sum())), f"{accuracy(prob_te[m], te.labels[m]):.3f}" if m.any() else "-"])
    rows.append(["train (fit)", str(len(tr.labels)), f"{accuracy(prob_tr, tr.labels):.3f}"])
    print_table("heading visibility: facing right or left, test crops", ["crops", "n", "accuracy"], rows)

    per_view = []
    for v, name in enumerate(VIEWS):
        m = te.views == v
        per_view.append(f"{name} {accuracy(prob_te[m], te.labels[m]):.3f}" if m.any() else f"{name} -")
    print(f"heading_visibility: accuracy {accuracy(prob_te, te.labels):.3f} on {len(te.labels)} test crops "
          f"(chance 0.5; train {len(tr.labels)}), " + ", ".join(per_view))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
