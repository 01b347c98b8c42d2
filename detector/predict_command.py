"""Detect objects and their eight cuboid corners in images: COCO-results JSON and overlays.

OUT is a folder of this command's own: predictions.json, images.json and one overlay per image,
OUT/<stem>.jpg (the source's name without its suffix). Sources sharing a stem (a/x.png, b/x.jpg)
get x.jpg, x-2.jpg, ... in the order they are listed; images.json names each image's overlay. OUT is
claimed for predict (.omnigen-job, omnigen.ownership) and a folder holding anything else is refused,
as is one that is, lies inside or holds a source image or folder: a dataset's images are hard
links into the trees they came from, and an overlay written there would be written into them.

An image that cannot be read (over the size caps, undecodable, gone) is skipped with a line on
stderr; the others are predicted and the run exits 1.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from omnigen.options import fraction, integer

IMGSZ_STEP = 32
"""--imgsz must be a multiple of this, the largest stride of a model without P6 (a P6 model's 64 is
checked once it is loaded)."""
IMGSZ_MAX = 4096
"""Largest --imgsz: the input of a 4K frame's long side; a batch of inputs this size already takes
gigabytes of activations."""
BATCH_MAX = 4096
MAX_DET_MAX = 100_000


def input_size(text: str) -> int:
    """argparse type of --imgsz: a whole number in [IMGSZ_STEP, IMGSZ_MAX], a multiple of IMGSZ_STEP."""
    value = integer(IMGSZ_STEP, IMGSZ_MAX)(text)
    if value % IMGSZ_STEP:
        raise argparse.ArgumentTypeError(f"{text} is not a multiple of {IMGSZ_STEP} (the network's stride)")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("weights", help="checkpoint (best.pt or last.pt of a run)")
    p.add_argument("sources", nargs="+", help="image files or folders of images")
    p.add_argument("--out", required=True, type=Path,
                   help="new or empty folder (or one of an earlier predict) for predictions.json, images.json and "
                        "overlays; never one that holds or lies inside a source")
    p.add_argument("--imgsz", type=input_size, default=None,
                   help=f"network input size, a multiple of {IMGSZ_STEP} (default: the training size)")
    p.add_argument("--conf", type=fraction(), default=0.25, help="confidence threshold, in [0, 1]")
    p.add_argument("--iou", type=fraction(), default=0.7, help="NMS IoU threshold, in [0, 1]")
    p.add_argument("--max-det", type=integer(1, MAX_DET_MAX), default=300, help="detections kept an image")
    p.add_argument("--batch", type=integer(1, BATCH_MAX), default=8, help="images per batch")
    p.add_argument("--no-overlays", action="store_true", help="write predictions.json only")
    p.add_argument("--vertical", choices=("lines", "off"), default=None,
                   help="lines: turn each image's detections' vertical edges to its vertical vanishing point, "
                        "fitted from them and refined with the image's line segments; off: the corners as the "
                        "network placed them (default: the run's recipe, predict.vertical)")


def claim_folder(out: Path, job: str, mark: bool = True) -> None:
    """omnigen.ownership.claim_output for a folder that only this job's own earlier runs may hold."""
    from omnigen.ownership import claim_output

    claim_output(out, job, lambda _: False, mark=mark)


def overlay_names(files: list[Path]) -> list[str]:
    """One distinct overlay file name per source: <stem>.jpg, then <stem>-2.jpg, <stem>-3.jpg, ...
    for later sources whose name is taken (two folders' x.png, or x.png beside x.jpg)."""
    taken: set[str] = set()
    names = []
    for path in files:
        name, n = f"{path.stem}.jpg", 1
        while name.lower() in taken:  # case-insensitive file systems see X.jpg and x.jpg as one
            n += 1
            name = f"{path.stem}-{n}.jpg"
        taken.add(name.lower())
        names.append(name)
    return names


def run(args: argparse.Namespace) -> int:
    from omnigen.detector.model.checkpoint import load_model
    from omnigen.detector.prediction.overlay import draw_detections
    from omnigen.detector.prediction.predict import (PredictOptions, coco_results, image_files, predict_images,
                                                     trained_imgsz, trained_vertical)
    from omnigen.files import atomic_write_bytes
    from omnigen.outputs import refuse_inputs, save_image
    from omnigen.progress import print_table, progress
    import orjson

    files = image_files(args.sources)
    if not files:
        raise ValueError(f"no images in {' '.join(map(str, args.sources))}")
    refuse_inputs(args.out, [args.weights, *args.sources, *files], "predict")
    claim_folder(args.out, "predict", mark=False)  # checked before the model loads, marked before the first write
    model, state = load_model(args.weights)
    opts = PredictOptions(imgsz=args.imgsz or trained_imgsz(state), conf=args.conf, iou=args.iou,
                          max_det=args.max_det, batch=args.batch,
                          vertical=args.vertical or trained_vertical(state))
    predicted = predict_images(model, files, opts)
    claim_folder(args.out, "predict")
    names = overlay_names(files)
    results, images, skipped = [], [], []
    for i, p in enumerate(progress(predicted, "predict", total=len(files))):
        if p.error is not None:
            skipped.append(p.path)
            print(f"skipped: {p.error}", file=sys.stderr)
            continue
        results.extend(r | {"file_name": str(p.path)} for r in coco_results(p.detections, i + 1))
        entry = {"id": i + 1, "file_name": str(p.path), "width": p.image.shape[1], "height": p.image.shape[0]}
        if not args.no_overlays:
            entry["overlay"] = names[i]
            save_image(draw_detections(p.image, p.detections, state["classes"]), args.out / names[i], "predict",
                       quality=90)
        images.append(entry)
    atomic_write_bytes(args.out / "predictions.json", orjson.dumps(results) + b"\n")
    atomic_write_bytes(args.out / "images.json", orjson.dumps(images) + b"\n")
    print_table(f"omnigen predict: {args.out}", ["images", "skipped", "detections", "classes"],
                [(len(images), len(skipped), len(results), len(state["classes"]))])
    return 1 if skipped else 0
