"""Export a checkpoint to ONNX: the forward pass with box and keypoint decoding, NMS left outside."""

from __future__ import annotations

import argparse
from pathlib import Path

OPSET = 18


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("weights", help="checkpoint (best.pt or last.pt)")
    p.add_argument("--out", required=True, type=Path, help="FILE.onnx")
    p.add_argument("--imgsz", type=int, default=640)
    p.add_argument("--check", action=argparse.BooleanOptionalAction, default=True,
                   help="run ONNX Runtime on a random input and compare with PyTorch (tolerance 1e-4)")


def export(model, path: Path, imgsz: int) -> None:
    """Trace `model.infer` at a fixed 1x3xSxS input named `images`, output `output0` (1, 4+nc+24, A)."""
    top = model.strides[-1]
    if imgsz <= 0 or imgsz % top:  # checked here: the model skips its own check while it is traced
        raise ValueError(f"--imgsz {imgsz}: the ONNX input must be a positive multiple of the largest stride {top}")
    import io

    import torch

    from detector.model import InferenceWrapper
    from omnigen.files import atomic_write_bytes

    buf = io.BytesIO()
    torch.onnx.export(InferenceWrapper(model.eval()), (torch.zeros(1, 3, imgsz, imgsz),), buf, opset_version=OPSET,
                      input_names=["images"], output_names=["output0"], dynamo=False)
    atomic_write_bytes(path, buf.getvalue())


def max_difference(model, path: Path, imgsz: int, seed: int = 0) -> float:
    """Largest absolute difference between ONNX Runtime and PyTorch on a random image."""
    import numpy as np
    import onnxruntime as ort
    import torch

    x = np.random.default_rng(seed).random((1, 3, imgsz, imgsz), dtype=np.float32)
    with torch.inference_mode():
        ref = model.eval().infer(torch.from_numpy(x)).numpy()
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"images": x})[0]
    return float(np.abs(got - ref).max())


def run(args: argparse.Namespace) -> int:
    from detector.checkpoint import load_model
    from omnigen.progress import print_table

    model, _ = load_model(args.weights)
    export(model, args.out, args.imgsz)
    rows = [("file", str(args.out)), ("input", f"1x3x{args.imgsz}x{args.imgsz}"), ("opset", OPSET)]
    if args.check:
        diff = max_difference(model, args.out, args.imgsz)
        rows.append(("max |ORT - PyTorch|", f"{diff:.2e}"))
        if diff > 1e-4:
            print_table("omnigen export onnx", ["", ""], rows)
            raise RuntimeError(f"{args.out}: ONNX Runtime differs from PyTorch by {diff:.2e} (> 1e-4)")
    print_table("omnigen export onnx", ["", ""], rows)
    return 0
