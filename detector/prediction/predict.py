"""Inference: images in, COCO-results detections out (boxes, eight keypoints, class, score).

Detections are mapped from the letterboxed input back to the original image, so they compare
directly with the dataset's annotations. Results follow pycocotools' results format (image_id,
category_id 1-based in the taxonomy's order, bbox as x y w h, keypoints as 24 numbers x y v with v
the corner's predicted visibility score, score) and add `frame_id` when the image is a dataset
frame, so evaluation never depends on the order images were listed in.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np
import torch

from omnigen.detector.data.samples import KeypointDataset, Letterbox, letterbox, split_frames
from omnigen.detector.model.crop_stage import refine_detections
from omnigen.detector.model.network import KeypointDetector
from omnigen.detector.model.outputs import Detections
from omnigen.detector.prediction.nms import postprocess
from omnigen.detector.recipe import RECIPE
from omnigen.conventions import NUM_KEYPOINTS

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp")

EVAL_CONF = 0.001
"""Confidence floor for evaluation: AP integrates over the whole score range, so keep low scores."""

EVAL_MAX_DET = 1000
"""Detections kept an image for evaluation (oks_eval.MAX_DETS, its maxDets, counts as many)."""

VERTICAL_MODES = ("lines", "off")
"""PredictOptions.vertical's: turn the vertical edges to the image's vanishing point, or not."""
PAD_MARGIN = 2
"""Pixels of the image left out next to the letterbox's padding when the snap looks for lines."""

EVAL_MULTI_LABEL = True
"""Evaluation scores every class of an anchor above EVAL_CONF, as Ultralytics' validation does
(its DetectionValidator, which pose validation inherits, runs NMS with multi_label=True): a class's
AP then ranks that class's scores, not only the anchors where it beat every other class. `omnigen
predict` keeps one class an anchor, what an application acts on."""


@dataclass
class PredictOptions:
    imgsz: int = 640
    conf: float = 0.25
    iou: float = 0.7
    max_det: int = 300
    batch: int = 8
    multi_label: bool = False  # every class above conf per anchor (evaluation), not only the best
    # a crop stage that names classes rescores the detections it refines (crop_stage.rescore);
    # False keeps the head's scores (docs/detector-training.md gives the difference)
    crop_classes: bool = True
    # "lines": each image's detections get their vertical edges turned to its vertical vanishing
    # point, fitted from them and refined with the image's line segments (vanishing.snap_vertical);
    # "off" keeps the corners as the network placed them
    vertical: str = "lines"

    def __post_init__(self) -> None:
        if self.vertical not in VERTICAL_MODES:
            raise ValueError(f"PredictOptions.vertical: one of {', '.join(VERTICAL_MODES)}, got {self.vertical!r}")


def snap_batch(images: list[np.ndarray], boxes: list[Letterbox], dets: list[Detections]) -> list[Detections]:
    """vanishing.snap_vertical of each letterboxed image's detections, on the image's own pixels
    (Letterbox.content_box) less PAD_MARGIN pixels on each padded side, or the letterbox's border
    would count as a long straight edge."""
    import cv2

    from omnigen.detector.prediction.vanishing import snap_vertical

    out = []
    for image, lb, d in zip(images, boxes, dets):
        region = snap_region(lb, *image.shape[1::-1])
        if not len(d) or region is None:
            out.append(d)
            continue
        x0, y0, x1, y1 = region
        gray = cv2.cvtColor(np.ascontiguousarray(image[y0:y1, x0:x1]), cv2.COLOR_RGB2GRAY)
        kp = d.keypoints[..., :2].detach().cpu().double().numpy() - np.array([x0, y0])
        snapped = snap_vertical(gray, kp, d.scores.detach().cpu().double().numpy()) + np.array([x0, y0])
        keypoints = d.keypoints.clone()
        keypoints[..., :2] = torch.from_numpy(snapped).to(keypoints)
        out.append(replace(d, keypoints=keypoints))
    return out


def snap_region(lb: Letterbox, width: int, height: int) -> tuple[int, int, int, int] | None:
    """x0, y0, x1, y1 (exclusive) of the letterboxed image's own pixels less PAD_MARGIN on each
    padded side, or None when nothing is left: an image 500 times wider than tall (10000 x 20) is
    one row of the input, which the margins remove, and an empty crop is no image to find lines in
    (its corners are kept as the network placed them)."""
    x0, y0, x1, y1 = lb.content_box(width, height)
    x0, y0 = x0 + (PAD_MARGIN if x0 > 0 else 0), y0 + (PAD_MARGIN if y0 > 0 else 0)
    x1, y1 = x1 - (PAD_MARGIN if x1 < width else 0), y1 - (PAD_MARGIN if y1 < height else 0)
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def to_image_coords(det: Detections, lb: Letterbox) -> dict[str, np.ndarray]:
    """Detections of the letterboxed input -> numpy arrays in original image pixels."""
    return batch_to_image_coords([det], [lb])[0]


def batch_to_image_coords(dets: list[Detections], boxes: list[Letterbox]) -> list[dict[str, np.ndarray]]:
    """A batch's detections -> numpy arrays in original image pixels, with one device-to-host copy
    for the whole batch (four per image would each wait for the device)."""
    counts = [len(d) for d in dets]
    flat = torch.cat([torch.cat([d.boxes.float(), d.scores.float()[:, None], d.classes.float()[:, None],
                                 d.keypoints.float().flatten(1)], 1) for d in dets]).cpu().numpy()
    out = []
    for part, lb in zip(np.split(flat, np.cumsum(counts)[:-1]), boxes):
        kp = part[:, 6:].reshape(-1, NUM_KEYPOINTS, 3).copy()
        kp[..., :2] = lb.to_image(kp[..., :2])
        out.append({"boxes": lb.to_image(part[:, :4].reshape(-1, 2, 2)).reshape(-1, 4), "scores": part[:, 4].copy(),
                    "classes": part[:, 5].astype(np.int64), "keypoints": kp})
    return out


def coco_results(det: dict[str, np.ndarray], image_id: int, frame_id: str | None = None) -> list[dict[str, Any]]:
    """One image's detections as pycocotools results."""
    out = []
    for b, s, c, k in zip(det["boxes"].tolist(), det["scores"].tolist(), det["classes"].tolist(),
                          det["keypoints"].reshape(len(det["scores"]), 3 * NUM_KEYPOINTS).tolist()):
        r = {"image_id": image_id, "category_id": int(c) + 1, "bbox": [b[0], b[1], b[2] - b[0], b[3] - b[1]],
             "keypoints": k, "score": s}
        if frame_id is not None:
            r["frame_id"] = frame_id
        out.append(r)
    return out


@torch.inference_mode()
def infer_batch(model: KeypointDetector, images: list[np.ndarray], boxes: list[Letterbox], opts: PredictOptions
                ) -> list[dict[str, np.ndarray]]:
    """Letterboxed uint8 images -> detections in original image coordinates.

    The batch crosses to a GPU as uint8 from pinned memory (a quarter of float32's bytes, no
    pageable staging copy) and is converted there; NHWC as stacked, which channels-last weights
    read without a transpose."""
    device = next(model.parameters()).device
    x = torch.from_numpy(np.stack(images))
    if device.type == "cuda":
        x = x.pin_memory()
    x = x.to(device, non_blocking=True).permute(0, 3, 1, 2).float().div_(255)
    pred = model.infer(x)
    # a crop stage that names classes may name a box's class otherwise than the head's best: a
    # single-label prediction then keeps every class score of each anchor through NMS, floored at
    # conf^2 (sqrt(s * p) > conf needs s > conf^2), and drops what the rescoring leaves under conf
    relabel = (model.crop_net is not None and model.crop_net.num_classes > 0 and opts.crop_classes
               and not opts.multi_label)
    dets = postprocess(pred.float(), model.cfg.num_classes, opts.conf ** 2 if relabel else opts.conf, opts.iou,
                       opts.max_det, multi_label=opts.multi_label, class_scores=relabel)
    if model.crop_net is not None:  # a crop-stage model places each detection's corners from its crop
        dets = refine_detections(model.crop_net, model.cfg.heading_crop, x, dets, rescore_classes=opts.crop_classes)
    if relabel:
        dets = [d.take(d.scores > opts.conf) for d in dets]
    if opts.vertical == "lines":
        dets = snap_batch(images, boxes, dets)
    return batch_to_image_coords(dets, boxes)


def one_label_per_box(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Multi-label results (EVAL_MULTI_LABEL) with each box's best-scoring detection alone: what an
    application reading the objects, one each, is given (a BEV map would count a box rated car and
    van twice). Class copies of a box share its image and its bbox exactly (one anchor's)."""
    best: dict[tuple[Any, ...], dict[str, Any]] = {}
    for r in results:
        key = (r.get("frame_id", r["image_id"]), *r["bbox"])
        if key not in best or r["score"] > best[key]["score"]:
            best[key] = r
    return list(best.values())


def batches(items: list[Any], size: int) -> Iterator[list[Any]]:
    for i in range(0, len(items), size):
        yield items[i:i + size]


def predict_frames(model: KeypointDetector, data: KeypointDataset, opts: PredictOptions,
                   show_progress: bool = False) -> list[dict[str, Any]]:
    """COCO results for the frames of a dataset split; image ids as omnigen.formats.coco.to_coco gives them
    (1-based frame order of the whole dataset), plus frame_id."""
    from omnigen.progress import progress

    model.eval()
    results: list[dict[str, Any]] = []
    ds = data.ds
    chunks = list(batches(list(range(len(data))), opts.batch))
    # Threads decode and letterbox the next batch while the model runs on this one (OpenCV
    # releases the GIL); before, the device waited for every image read in turn.
    with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
        pending = [pool.submit(data.sample, i) for i in chunks[0]] if chunks else []
        for k in progress(range(len(chunks)), "predict", disable=not show_progress):
            samples = [f.result() for f in pending]
            pending = [pool.submit(data.sample, i) for i in chunks[k + 1]] if k + 1 < len(chunks) else []
            dets = infer_batch(model, [s.image for s in samples], [s.letterbox for s in samples], opts)
            for s, d in zip(samples, dets):
                results.extend(coco_results(d, s.frame_index + 1, ds.table.frame_id[s.frame_index]))
    return results


def trained_imgsz(state: dict[str, Any], default: int = 640) -> int:
    """The input size a checkpoint was trained at: predicting at another size shows the model
    objects at scales it did not learn."""
    return int(state.get("train_config", {}).get("imgsz", default))


def trained_vertical(state: dict[str, Any]) -> str:
    """How the checkpoint's run predicts vertical edges (its recipe's predict.vertical, checked when
    the checkpoint loaded), the validated recipe's for a checkpoint written before runs kept it:
    `omnigen train predict.vertical=off` then predicts as it was told without --vertical."""
    return state.get("train_config", {}).get("predict", {}).get("vertical", RECIPE.predict.vertical)


def load_for_prediction(weights: str | Path, device: str | None = None) -> tuple[KeypointDetector, dict[str, Any]]:
    """A checkpoint's model, in eval mode on `device` (default: CUDA when there is one: a
    checkpoint loads onto the CPU, where a GPU machine's evaluation would otherwise run), and the
    checkpoint, whose taxonomy and training size the prediction needs."""
    from omnigen.detector.model.checkpoint import load_model

    model, state = load_model(weights)
    return model.to(device or ("cuda" if torch.cuda.is_available() else "cpu")), state


def predict_split(model: KeypointDetector, state: dict[str, Any], dataset_root: str | Path, split: str | None = "test",
                  imgsz: int | None = None, batch: int = 8, conf: float = EVAL_CONF,
                  multi_label: bool = EVAL_MULTI_LABEL, crop_classes: bool = True, vertical: str | None = None
                  ) -> list[dict[str, Any]]:
    """Detections of a loaded model (load_for_prediction) on a dataset split, ready for `omnigen
    eval`, at the training input size unless `imgsz` says otherwise. A caller that predicts twice
    with one model (with and without its crop stage: `model.crop_net = None` keeps the head's own
    corners), or reads the checkpoint's taxonomy first, loads it
    once. `multi_label=False` keeps one class an anchor, as `omnigen predict` does
    (EVAL_MULTI_LABEL). `crop_classes=False` keeps the head's scores where the crop stage names classes;
    `vertical` is PredictOptions' (None: the run's, trained_vertical).
    """
    from omnigen.detector.model.checkpoint import checkpoint_taxonomy

    imgsz = imgsz or trained_imgsz(state)
    data = KeypointDataset(dataset_root, checkpoint_taxonomy(state), imgsz, split_frames(dataset_root, split))
    return predict_frames(model, data, PredictOptions(imgsz=imgsz, conf=conf, batch=batch, max_det=EVAL_MAX_DET,
                                                      multi_label=multi_label, crop_classes=crop_classes,
                                                      vertical=vertical or trained_vertical(state)),
                          show_progress=True)


def predict_dataset(weights: str | Path, dataset_root: str | Path, split: str | None = "test",
                    imgsz: int | None = None, batch: int = 8, conf: float = EVAL_CONF,
                    device: str | None = None, multi_label: bool = EVAL_MULTI_LABEL, vertical: str | None = None
                    ) -> list[dict[str, Any]]:
    """predict_split of a checkpoint file, loaded onto `device` (load_for_prediction)."""
    model, state = load_for_prediction(weights, device)
    return predict_split(model, state, dataset_root, split, imgsz, batch, conf, multi_label, vertical=vertical)


def image_files(paths: Iterable[str | Path]) -> list[Path]:
    """Files given, and the images inside folders given (sorted); anything else is an error."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out.extend(sorted(q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES))
        elif p.is_file():
            if p.suffix.lower() not in IMAGE_SUFFIXES:
                raise ValueError(f"{p}: not an image ({', '.join(IMAGE_SUFFIXES)})")
            out.append(p)
        else:
            raise FileNotFoundError(f"{p}: no such file or folder")
    return out


@dataclass
class PredictedImage:
    """One source image's outcome: its pixels and detections, or why it was skipped."""

    path: Path
    image: np.ndarray | None = None  # RGB uint8 (H, W, 3)
    detections: dict[str, np.ndarray] | None = None  # to_image_coords'
    error: str | None = None  # the skip: the file and the reason (an ImageError's text)


def read_source_image(path: Path) -> np.ndarray:
    """RGB uint8 pixels of an image given to `omnigen predict`, the header's size capped before
    decoding (omnigen.images); decoded by OpenCV as training decodes (detector.data.read_image)."""
    import cv2

    from omnigen.images import ImageError, read_image_bytes

    data, _ = read_image_bytes(path)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ImageError(path, "unreadable image: OpenCV cannot decode it")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def check_input_size(model: KeypointDetector, imgsz: int) -> None:
    """The network takes inputs whose side is a multiple of its largest stride (32, or 64 with P6)."""
    stride = model.strides[-1]
    if imgsz % stride:
        raise ValueError(f"--imgsz {imgsz}: this model takes multiples of {stride}, its largest stride")


def predict_images(model: KeypointDetector, files: list[Path], opts: PredictOptions) -> Iterator[PredictedImage]:
    """A PredictedImage per file, in order. An image that cannot be read (missing, not a regular
    file, over the size caps, undecodable) is skipped with its reason; the others are predicted.
    The input size is checked here, before the first image is read."""
    check_input_size(model, opts.imgsz)
    return _predict_images(model, files, opts)


def _read_or_skip(path: Path) -> PredictedImage:
    from omnigen.images import ImageError

    try:
        return PredictedImage(path, read_source_image(path))
    except ImageError as exc:
        return PredictedImage(path, error=str(exc))


def _predict_images(model: KeypointDetector, files: list[Path], opts: PredictOptions) -> Iterator[PredictedImage]:
    model.eval()
    for chunk in batches(files, opts.batch):
        read = [_read_or_skip(f) for f in chunk]
        good = [r for r in read if r.error is None]
        if good:
            boxed = [letterbox(r.image, opts.imgsz) for r in good]
            for r, det in zip(good, infer_batch(model, [b[0] for b in boxed], [b[1] for b in boxed], opts)):
                r.detections = det
        yield from read
