"""Ultralytics' YOLO11n-pose beside the bundled detector: the same data, the same minutes, scored by `omnigen eval`.

    python benchmarks/peer_ultralytics.py --work WORK [--minutes 7] [--imgsz 640] [--batch 64] [--device cuda]
    python benchmarks/gpu_validate.py --work WORK --peer ...        # the same, after gpu_validate's own run

WORK is benchmarks/gpu_validate.py's working folder: its merged dataset WORK/uov (the test split
`make validate`'s) is exported with `omnigen export yolo`, YOLO11n-pose is built from its model
YAML (from scratch: no weights are downloaded, the machine may have no network) and trained with
Ultralytics' own `time` budget, its last weights (as ours: no checkpoint picked by the test score)
predict the test split, the predictions are turned into our COCO-results form and `omnigen eval`
scores them as it scores ours. So the tool users would otherwise pick is compared on one machine,
on the same frames, by the same metric. Writes WORK/peer/ (the export, Ultralytics' run,
test-predictions.json, eval.json, result.json) and prints one side-by-side line.

Ultralytics needs torchvision, which GPU images have; where it cannot be imported this says so in
one line and exits 0.
"""

from __future__ import annotations

import argparse
import csv
import importlib.metadata
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# the standard library alone: ultralytics and omnigen are imported once use_site has run
from benchmarks.common import Runner, fmt, metric_row, stale, synthetic_row, usable_cores, use_site  # noqa: E402

MODEL_YAML = "yolo11n-pose.yaml"
MODEL = "YOLO11n-pose"
EVAL_CONF = 0.001  # as omnigen.detector.prediction.predict.EVAL_CONF: AP integrates over the whole score range
MAX_DETECTIONS = 1000  # as our evaluation's predictions


def _numpy(x: Any):
    """A torch tensor or an array as a numpy array."""
    import numpy as np

    return x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)


def ultralytics_detections(result: Any) -> dict[str, Any]:
    """One Ultralytics pose `Results` as omnigen.detector.prediction.predict's detections: boxes x1 y1 x2 y2, scores,
    0-based classes, keypoints (N, 8, 3) x y and the corner's confidence, in our pixel convention.

    Ultralytics measures pixels from the image's top-left corner, our pixel centres are integers
    (omnigen/formats/yolo.py shifts the labels by +0.5 on export), so every coordinate moves by -0.5.
    """
    import numpy as np

    from omnigen.conventions import NUM_KEYPOINTS

    boxes = _numpy(result.boxes.xyxy).astype(np.float64).reshape(-1, 4) - 0.5
    n = len(boxes)
    keypoints = np.zeros((n, NUM_KEYPOINTS, 3))
    if result.keypoints is not None and n:
        data = _numpy(result.keypoints.data).astype(np.float64)  # (n, 8, 3): x, y, confidence
        keypoints[..., :2] = data[..., :2] - 0.5
        keypoints[..., 2] = data[..., 2] if data.shape[-1] == 3 else 1.0  # no visibility head: as sure as its box
    return {"boxes": boxes, "scores": _numpy(result.boxes.conf).astype(np.float64).reshape(n),
            "classes": _numpy(result.boxes.cls).astype(np.int64).reshape(n), "keypoints": keypoints}


def coco_predictions(results: list[Any], frame_index: dict[str, int]) -> list[dict[str, Any]]:
    """Ultralytics results over exported test images (named `<frame_id>.<ext>`) as COCO results
    for `omnigen eval`: image ids as omnigen.formats.coco gives them (1-based frame order), plus frame_id."""
    from omnigen.detector.prediction.predict import coco_results

    out = []
    for r in results:
        frame_id = Path(r.path).stem
        if frame_id not in frame_index:
            raise ValueError(f"{r.path}: no frame {frame_id!r} in the dataset the export was made from")
        out.extend(coco_results(ultralytics_detections(r), frame_index[frame_id] + 1, frame_id))
    return out


def epochs_trained(run_dir: Path) -> int:
    path = run_dir / "results.csv"
    return len(list(csv.DictReader(path.read_text().splitlines()))) if path.exists() else 0


def main(argv: list[str] | None = None) -> int:
    cores = usable_cores()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="gpu_validate.py's working folder (WORK/uov)")
    ap.add_argument("--minutes", type=float, default=7.0, help="Ultralytics' training budget (its `time`)")
    ap.add_argument("--imgsz", type=int, default=640)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--workers", type=int, default=max(0, cores - 2))
    ap.add_argument("--device", default=None, help="cuda, cpu (default: cuda when there is one)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    work = args.work.resolve()
    use_site(work / "site")  # what gpu_validate installed there
    peer = work / "peer"
    os.environ.setdefault("YOLO_CONFIG_DIR", str(peer / "ultralytics-config"))  # not the home folder
    try:
        from ultralytics import YOLO
    except ImportError as exc:
        print(f"peer_ultralytics: ultralytics cannot be imported here ({exc}): no peer run "
              "(pip install ultralytics; it needs torchvision)")
        return 0
    import torch

    from omnigen.dataset import Dataset
    from omnigen.files import atomic_write_json, atomic_write_text
    from omnigen.splits import read_split

    uov = work / "uov"
    if not (uov / "manifest.json").exists():
        raise SystemExit(f"peer_ultralytics: {uov} is no merged dataset: run benchmarks/gpu_validate.py --work {work} first")
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    peer.mkdir(parents=True, exist_ok=True)
    run = Runner(peer, "peer_ultralytics")
    yolo = peer / "yolo"
    run(["export", "yolo", str(uov), "--out", str(yolo)], yolo / "data.yaml")

    run_dir = peer / "train"
    weights = run_dir / "weights" / "last.pt"
    preds, report_path = peer / "test-predictions.json", peer / "eval.json"
    stamp = f"{MODEL_YAML} minutes={args.minutes:g} imgsz={args.imgsz} batch={args.batch} seed={args.seed}"
    if stale(run_dir / "done", stamp):  # trained with other arguments: train, predict and score again
        shutil.rmtree(run_dir)
        preds.unlink(missing_ok=True)
        report_path.unlink(missing_ok=True)
        run.forget(run_dir)
    if not (run_dir / "done").exists():
        t = time.perf_counter()
        YOLO(MODEL_YAML, task="pose").train(
            data=str(yolo / "data.yaml"), time=args.minutes / 60, epochs=1000, imgsz=args.imgsz, batch=args.batch,
            workers=args.workers, device=0 if device.startswith("cuda") else "cpu", project=str(peer), name="train",
            exist_ok=True, pretrained=False, plots=False, val=False, cache="ram", seed=args.seed, verbose=False)
        run.record(f"YOLO({MODEL_YAML}).train({run_dir}, time={args.minutes / 60:.4f} h)", time.perf_counter() - t)
        atomic_write_text(run_dir / "done", stamp + "\n")

    if not preds.exists():
        t = time.perf_counter()
        ds = Dataset.open(uov, show_progress=False)
        frame_index = {f: ds.index_of(f) for f in read_split(uov, "test")}
        images = sorted(p for p in (yolo / "images" / "test").iterdir())
        results = YOLO(str(weights), task="pose").predict(
            [str(p) for p in images], imgsz=args.imgsz, conf=EVAL_CONF, max_det=MAX_DETECTIONS, batch=args.batch,
            device=0 if device.startswith("cuda") else "cpu", stream=True, verbose=False)
        atomic_write_text(preds, json.dumps(coco_predictions(list(results), frame_index)))
        run.record(f"YOLO({weights}).predict(test)", time.perf_counter() - t)
    run(["eval", str(preds), str(uov), "--split", "test", "--out", str(report_path)], report_path)
    report = json.loads(report_path.read_text())

    result = {"model": MODEL, "ultralytics": importlib.metadata.version("ultralytics"), "minutes": args.minutes,  # the stamp's
              "imgsz": args.imgsz, "batch": args.batch, "device": device, "epochs": epochs_trained(run_dir),
              "train_seconds": round(run.seconds(f"YOLO({MODEL_YAML}).train({run_dir},"), 1),
              "synthetic": metric_row(synthetic_row(report)), "overall": metric_row(report["report"]["rows"][0])}
    atomic_write_json(peer / "result.json", result, indent=2)
    ours_path = work / "results.json"
    ours = json.loads(ours_path.read_text())["synthetic"] if ours_path.exists() else {}
    s = result["synthetic"]
    print(f"peer_ultralytics: synthetic mAP50:95 bundled n+P2 {fmt(ours.get('oks_map50_95'))} vs {MODEL} "
          f"{fmt(s['oks_map50_95'])}; AP50 {fmt(ours.get('ap_oks50'))} vs {fmt(s['ap_oks50'])}; adherence "
          f"{fmt(ours.get('ground_adherence_deg'), 2)} vs {fmt(s['ground_adherence_deg'], 2)} deg "
          f"({result['epochs']} epochs in {args.minutes:g} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
