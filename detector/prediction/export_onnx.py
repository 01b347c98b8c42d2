"""Export a checkpoint to ONNX: the forward pass with box and keypoint decoding, NMS left outside.

A crop-stage model (DetectorConfig.heading_crop, detector/model/crop_stage.py) places each detection's
corners and front from its crop after NMS, so it exports a second graph beside the first,
FILE-crops.onnx (`crop_stage_path`): the input image, the kept boxes and keypoints in, the
keypoints with the crops' corners out, and for a stage that names classes (crop_classes) their
probabilities (`class_probs`), by which a caller rescores each detection as
crop_stage.rescore does: sqrt(score * p[class]).

Neither graph turns the vertical edges to the image's vertical vanishing point, as `omnigen
predict` does by default (`--vertical lines`): that step reads the image's line segments with
OpenCV's detector, outside any network. A caller of the graphs applies
omnigen.detector.prediction.vanishing.snap_vertical to each image's refined corners, in the pixels of the
image the graph saw less its letterbox padding (predict.snap_batch shows how), or leaves the
corners as the network placed them (`--vertical off`).

Both files start with the job's mark, ONNX metadata {"omnigen": "export onnx"}, so a rerun
recognises them by their first bytes and replaces them; any other file at --out (the checkpoint
itself, say) is refused before anything is written (omnigen.outputs)."""

from __future__ import annotations

import argparse
from pathlib import Path

from omnigen.options import integer

OPSET = 18
JOB = "export onnx"
MAX_IMGSZ = 8192
"""The largest --imgsz: far above any training size, and below the sizes whose traced input (and
the check's two forward passes) would exhaust a machine's memory."""


def onnx_mark() -> bytes:
    """A serialized ModelProto holding only the mark (metadata_props omnigen = export onnx).

    Written in front of the exported model: protobuf merges concatenated messages, so readers
    (onnx.load, ONNX Runtime) see one model with the mark among its metadata_props, while the
    mark sits in the file's first bytes, not after the weights where a serializer puts field 14.
    """
    import onnx

    from omnigen.outputs import MARK_KEY

    return onnx.ModelProto(metadata_props=[onnx.StringStringEntryProto(key=MARK_KEY, value=JOB)]).SerializeToString()


def made_by_export_onnx(path: Path) -> bool:
    """A file this job wrote: it starts with onnx_mark(). Reads only that many bytes."""
    from omnigen.outputs import read_prefix

    mark = onnx_mark()
    return read_prefix(path, len(mark)) == mark


def write_onnx(path: Path, model_bytes: bytes) -> None:
    """The marked model, by temporary name and rename."""
    from omnigen.files import atomic_write_bytes

    atomic_write_bytes(path, onnx_mark() + model_bytes)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("weights", help="checkpoint (best.pt or last.pt)")
    p.add_argument("--out", required=True, type=Path,
                   help="FILE.onnx (new, or written by export onnx before; never the checkpoint)")
    p.add_argument("--imgsz", type=integer(1, MAX_IMGSZ), default=None,
                   help="square input size (default: the size the checkpoint was trained at, 640 if it does not say)")
    p.add_argument("--dynamic", action="store_true",
                   help="let height and width vary (any multiple of the largest stride); --imgsz is then the "
                        "size traced and checked")
    p.add_argument("--check", action=argparse.BooleanOptionalAction, default=True,
                   help="run ONNX Runtime on a random input and compare with PyTorch (tolerance 1e-4)")


DYNAMIC_AXES = {"images": {2: "height", 3: "width"}, "output0": {2: "anchors"}}


def export(model, path: Path, imgsz: int, dynamic: bool = False) -> None:
    """Trace `model.infer` at a 1x3xSxS input named `images`, output `output0` (1, 4+nc+24, A).

    Fixed size by default (what most runtimes optimise best); `dynamic` names height, width and
    the anchor count as free axes, which the graph allows because the model makes no Python-side
    decision on the traced size."""
    top = model.strides[-1]
    if imgsz <= 0 or imgsz % top:  # checked here: the model skips its own check while it is traced
        raise ValueError(f"--imgsz {imgsz}: the ONNX input must be a positive multiple of the largest stride {top}")
    import io

    import torch

    from omnigen.detector.model.network import InferenceWrapper

    buf = io.BytesIO()
    torch.onnx.export(InferenceWrapper(model.eval()), (torch.zeros(1, 3, imgsz, imgsz),), buf, opset_version=OPSET,
                      input_names=["images"], output_names=["output0"], dynamo=False,
                      dynamic_axes=DYNAMIC_AXES if dynamic else None)
    write_onnx(path, buf.getvalue())


def crop_stage_path(path: Path) -> Path:
    """Where a crop-stage model's second graph goes: FILE.onnx -> FILE-crops.onnx."""
    return path.with_name(f"{path.stem}-crops{path.suffix or '.onnx'}")


CROP_STAGE_AXES = {"boxes": {0: "detections"}, "keypoints": {0: "detections"}, "refined": {0: "detections"},
                   "class_probs": {0: "detections"}}


def export_crop_stage(model, path: Path, imgsz: int, dynamic: bool = False) -> None:
    """Trace the crop stage (crop_stage.RefineWrapper) with three example detections; the
    detection count is always a free axis, height and width with `dynamic`."""
    import io

    import torch

    from omnigen.detector.model.crop_stage import RefineWrapper

    boxes = torch.tensor([[8.0, 8.0, 40.0, 30.0], [20.0, 4.0, 30.0, 44.0], [0.0, 0.0, 16.0, 16.0]])
    outputs = ["refined"] + (["class_probs"] if model.crop_net.num_classes else [])
    axes = {k: v for k, v in CROP_STAGE_AXES.items() if k != "class_probs" or k in outputs}
    axes.update({"images": {2: "height", 3: "width"}} if dynamic else {})
    buf = io.BytesIO()
    torch.onnx.export(RefineWrapper(model.crop_net.eval(), model.cfg.heading_crop),
                      (torch.zeros(1, 3, imgsz, imgsz), boxes, torch.zeros(3, 8, 3)), buf, opset_version=OPSET,
                      input_names=["images", "boxes", "keypoints"], output_names=outputs, dynamo=False,
                      dynamic_axes=axes)
    write_onnx(path, buf.getvalue())


def crop_stage_max_difference(model, path: Path, imgsz: int | tuple[int, int], seed: int = 0) -> float:
    """Largest absolute difference between ONNX Runtime and PyTorch for the crop stage, on a random
    image and five random detections of size `imgsz`."""
    import numpy as np
    import onnxruntime as ort
    import torch

    from omnigen.detector.model.crop_stage import RefineWrapper

    h, w = (imgsz, imgsz) if isinstance(imgsz, int) else imgsz
    rng = np.random.default_rng(seed)
    x = rng.random((1, 3, h, w), dtype=np.float32)
    size = np.array([w, h], dtype=np.float32)
    xy = rng.random((5, 2), dtype=np.float32) * size
    boxes = np.concatenate([xy, xy + rng.random((5, 2), dtype=np.float32) * 40 + 4], 1)
    kpts = np.concatenate([rng.random((5, 8, 2), dtype=np.float32) * size, rng.random((5, 8, 1), dtype=np.float32)], 2)
    with torch.inference_mode():
        ref = RefineWrapper(model.crop_net.eval(), model.cfg.heading_crop)(
            torch.from_numpy(x), torch.from_numpy(boxes), torch.from_numpy(kpts))
    refs = [r.numpy() for r in (ref if isinstance(ref, tuple) else (ref,))]
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"images": x, "boxes": boxes, "keypoints": kpts})
    if len(got) != len(refs):
        raise ValueError(f"{path}: {len(got)} outputs, the crop stage gives {len(refs)}")
    return max(float(np.abs(g - r).max()) for g, r in zip(got, refs))


def max_difference(model, path: Path, imgsz: int | tuple[int, int], seed: int = 0) -> float:
    """Largest absolute difference between ONNX Runtime and PyTorch on a random image of size
    `imgsz` (square) or (height, width)."""
    import numpy as np
    import onnxruntime as ort
    import torch

    h, w = (imgsz, imgsz) if isinstance(imgsz, int) else imgsz
    x = np.random.default_rng(seed).random((1, 3, h, w), dtype=np.float32)
    with torch.inference_mode():
        ref = model.eval().infer(torch.from_numpy(x)).numpy()
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"images": x})[0]
    return float(np.abs(got - ref).max())


def run(args: argparse.Namespace) -> int:
    from omnigen.detector.model.checkpoint import load_model
    from omnigen.detector.prediction.predict import trained_imgsz
    from omnigen.outputs import check_output_file
    from omnigen.progress import print_table

    # before the load: a mistaken --out (the checkpoint itself, say) fails at once
    check_output_file(args.out, JOB, made_by_export_onnx, inputs=[args.weights])
    model, state = load_model(args.weights)
    # The training size by default: a model exported at another fixed size refuses the images it
    # was trained on, and sees objects at scales it did not learn.
    imgsz = trained_imgsz(state) if args.imgsz is None else args.imgsz
    stage = crop_stage_path(args.out) if model.crop_net is not None else None
    if stage is not None:  # both files checked before either is written
        check_output_file(stage, JOB, made_by_export_onnx, inputs=[args.weights])
    export(model, args.out, imgsz, args.dynamic)
    if stage is not None:
        export_crop_stage(model, stage, imgsz, args.dynamic)
    top = model.strides[-1]
    shape = f"1x3xHxW (multiples of {top}; traced at {imgsz})" if args.dynamic else f"1x3x{imgsz}x{imgsz}"
    rows = [("file", str(args.out)), ("input", shape), ("opset", OPSET)]
    if stage is not None:
        rows.append(("crop stage (after NMS)", str(stage)))
    if args.check:
        # dynamic: also at a non-square size other than the traced one, the point of the option
        sizes = [imgsz, (imgsz, imgsz + top)] if args.dynamic else [imgsz]
        diff = max(max_difference(model, args.out, size) for size in sizes)
        if stage is not None:
            diff = max([diff] + [crop_stage_max_difference(model, stage, size) for size in sizes])
        rows.append(("max |ORT - PyTorch|", f"{diff:.2e}"))
        if diff > 1e-4:
            print_table("omnigen export onnx", ["", ""], rows)
            raise RuntimeError(f"{args.out}: ONNX Runtime differs from PyTorch by {diff:.2e} (> 1e-4)")
    print_table("omnigen export onnx", ["", ""], rows)
    return 0
