"""Speed of `omnigen eval` on 10,000 frames (~7.5 objects each) with noisy predictions (target: under 60 s).

Three fake sources (synthetic in all three views, kitti, dair-v2x-i; cached in the temp folder)
are joined in memory into one 10,000-frame dataset, so the per-source and per-view groups all
exist. Predictions are the ground-truth corners with Gaussian pixel noise, a few dropped objects
and a few false positives, with random scores. Times `omnigen.detector.evaluation.oks_eval.evaluate` end to end
(COCO view, matching, every group, class and size, ground-plane adherence with omnigen.detector.bev.lift): median of
--repeats runs.

    .venv/bin/python benchmarks/bench_eval.py
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks.common import fake_dataset  # noqa: E402
from omnigen.detector.evaluation.oks_eval import evaluate  # noqa: E402
from omnigen.formats.coco import to_coco  # noqa: E402
from omnigen.dataset import Dataset  # noqa: E402
from omnigen.tables import FrameTable, ObjectTable  # noqa: E402


def joined_dataset(frames: int) -> Dataset:
    """Half synthetic, a quarter kitti, a quarter dair-v2x-i, as one Dataset (no folder of its own)."""
    parts = [("synthetic", frames - 2 * (frames // 4)), ("kitti", frames // 4), ("dair-v2x-i", frames // 4)]
    opened = [Dataset.open(fake_dataset(f"eval-{src}-{n}", n, source=src, seed=k, images=False), show_progress=False)
              for k, (src, n) in enumerate(parts)]
    frame_offsets = np.cumsum([0] + [len(d) for d in opened])[:-1].tolist()
    objects = ObjectTable.concat([d.objects for d in opened], frame_offsets)
    offsets = np.concatenate([[0], np.cumsum(np.bincount(objects.frame, minlength=sum(len(d) for d in opened)))])
    return Dataset(Path(tempfile.mkdtemp(prefix="omnigen-bench-eval-")), FrameTable.concat([d.table for d in opened]),
                   offsets, objects, None, {"name": "bench-eval"})


def noisy_predictions(ds: Dataset, rng: np.random.Generator, noise: float = 0.04) -> list[dict]:
    """Corner noise of `noise` x sqrt(box area) pixels: the fixture's 64x40 images hold objects a few
    pixels wide, where a fixed pixel noise would leave little to match."""
    coco = to_coco(ds)  # fine taxonomy: one annotation per object, in object order
    projected = np.nan_to_num(ds.objects.keypoints)  # all eight corners, also those outside the image
    out = []
    for a, true_kp in zip(coco["annotations"], projected):
        if rng.random() < 0.05:  # missed
            continue
        kp = np.zeros((8, 3))
        x, y, w, h = a["bbox"]
        kp[:, :2] = true_kp + rng.normal(0, noise * math.sqrt(max(a["area"], 1.0)), (8, 2))
        kp[:, 2] = 2
        out.append({"image_id": a["image_id"], "category_id": a["category_id"], "keypoints": kp.ravel().tolist(),
                    "bbox": [x, y, w, h], "score": float(rng.uniform(0.3, 1.0))})
        if rng.random() < 0.1:  # a false positive nearby
            fp = kp.copy()
            fp[:, :2] += rng.normal(0, 20, 2)
            out.append({"image_id": a["image_id"], "category_id": a["category_id"], "keypoints": fp.ravel().tolist(),
                        "bbox": [x, y, w, h], "score": float(rng.uniform(0.0, 0.6))})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    ds = joined_dataset(args.frames)
    preds = noisy_predictions(ds, np.random.default_rng(0))
    times, times_2d = [], []
    for _ in range(args.repeats):
        t = time.perf_counter()
        report = evaluate(ds, preds)
        times.append(time.perf_counter() - t)
        t = time.perf_counter()
        evaluate(ds, preds, adherence=False)
        times_2d.append(time.perf_counter() - t)

    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}")
    print(f"dataset: {len(ds)} frames, {len(ds.objects)} objects; {len(preds)} predictions")
    print(f"omnigen eval (evaluate, all groups, adherence): median {statistics.median(times):.1f} s over "
          f"{args.repeats} runs (min {min(times):.1f}, max {max(times):.1f}); target < 60 s")
    print(f"  of which keypoint metrics alone (--no-adherence): median {statistics.median(times_2d):.1f} s")
    r = report.row("overall")
    print(f"overall: images {r.images}, objects {r.objects}, OKS mAP50:95 {r.oks_map50_95:.3f}, AP50 {r.ap_oks50:.3f}, "
          f"P {r.precision:.3f} R {r.recall:.3f} F1 {r.f1:.3f} at conf {r.conf_threshold:.3f}, "
          f"adherence {r.ground_adherence_deg:.2f} deg over {r.adherence_objects} matches")
    for note in report.notes:
        print(f"note: {note}")


if __name__ == "__main__":
    main()
