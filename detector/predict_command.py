"""Detect objects and their eight cuboid corners in images: COCO-results JSON and overlays."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("weights", help="checkpoint (best.pt or last.pt of a run)")
    p.add_argument("sources", nargs="+", help="image files or folders of images")
    p.add_argument("--out", required=True, type=Path, help="folder for predictions.json and overlay images")
    p.add_argument("--imgsz", type=int, default=None, help="network input size (default: the training size)")
    p.add_argument("--conf", type=float, default=0.25, help="confidence threshold")
    p.add_argument("--iou", type=float, default=0.7, help="NMS IoU threshold")
    p.add_argument("--max-det", type=int, default=300)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--no-overlays", action="store_true", help="write predictions.json only")
    p.add_argument("--vertical", choices=("lines", "off"), default="lines",
                   help="lines (default): turn each image's detections' vertical edges to its vertical vanishing "
                        "point, fitted from them and refined with the image's line segments; off: the corners as "
                        "the network placed them")


def run(args: argparse.Namespace) -> int:
    from omnigen.detector.checkpoint import load_model
    from omnigen.detector.overlay import draw_detections
    from omnigen.detector.predict import PredictOptions, coco_results, image_files, predict_images, trained_imgsz
    from omnigen.files import atomic_write_bytes
    from omnigen.progress import print_table, progress
    import orjson

    files = image_files(args.sources)
    if not files:
        raise ValueError(f"no images in {' '.join(map(str, args.sources))}")
    model, state = load_model(args.weights)
    args.out.mkdir(parents=True, exist_ok=True)
    opts = PredictOptions(imgsz=args.imgsz or trained_imgsz(state), conf=args.conf, iou=args.iou,
                          max_det=args.max_det, batch=args.batch, vertical=args.vertical)
    results, images = [], []
    for i, (path, image, det) in enumerate(progress(predict_images(model, files, opts), "predict", total=len(files))):
        results.extend(r | {"file_name": str(path)} for r in coco_results(det, i + 1))
        images.append({"id": i + 1, "file_name": str(path), "width": image.shape[1], "height": image.shape[0]})
        if not args.no_overlays:
            draw_detections(image, det, state["classes"]).save(args.out / f"{path.stem}.jpg", quality=90)
    atomic_write_bytes(args.out / "predictions.json", orjson.dumps(results) + b"\n")
    atomic_write_bytes(args.out / "images.json", orjson.dumps(images) + b"\n")
    print_table(f"omnigen predict: {args.out}", ["images", "detections", "classes"],
                [(len(files), len(results), len(state["classes"]))])
    return 0
