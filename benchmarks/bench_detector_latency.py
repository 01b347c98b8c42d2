"""CPU latency of the detector at 640: n without and with P2, in PyTorch and ONNX Runtime, beside
Ultralytics' YOLO11n-pose and YOLOv8n-pose-P2 (ONNX anchors in /work/shared/anchors, timed in the
same run with the same settings). Target: n+P2 in ONNX Runtime within 1.5x of YOLO11n-pose.

Settings: batch 1, 640 x 640, median of --repeats runs after --warmup runs; ONNX Runtime CPU
provider with 2 intra-op threads and 1 inter-op thread; PyTorch with 2 threads, inference_mode,
batch-norms folded. Random weights (latency does not depend on them).

    .venv/bin/python benchmarks/bench_detector_latency.py
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.detector.model.network import DetectorConfig, InferenceWrapper, KeypointDetector, gflops  # noqa: E402

ANCHORS = Path("/work/shared/anchors")
ANCHOR_FILES = {
    "yolo11n-pose (Ultralytics)": ("ultralytics-yolo11n-pose-k8-640.onnx", 6.9),
    "yolov8n-pose-p2 (Ultralytics)": ("ultralytics-yolov8n-pose-p2-k8-640.onnx", 13.4),
}
TARGET_RATIO = 1.5


def export_onnx(model: KeypointDetector, path: Path, imgsz: int) -> None:
    """Export `model.infer` (batch-norms folded) with the TorchScript-based exporter, opset 18."""
    x = torch.zeros(1, 3, imgsz, imgsz)
    torch.onnx.export(InferenceWrapper(model), (x,), str(path), opset_version=18, dynamo=False,
                      input_names=["images"], output_names=["output"])


def time_interleaved(fns: dict[str, "callable"], warmup: int, repeats: int) -> dict[str, float]:
    """Median milliseconds per call of each function, the functions called in turn within each
    repeat: on a shared, noisy machine, load drift then hits every model alike."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    return {name: statistics.median(ts) * 1000 for name, ts in times.items()}


def ort_runner(path: Path, imgsz: int):
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 2
    opts.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    name = sess.get_inputs()[0].name
    x = np.random.default_rng(0).random((1, 3, imgsz, imgsz), dtype=np.float32)
    return lambda: sess.run(None, {name: x})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--imgsz", type=int, default=640)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--backbone", default="c3k2")
    args = ap.parse_args()
    torch.set_num_threads(2)

    flops: dict[str, float] = {}
    fns = {}
    x = torch.rand(1, 3, args.imgsz, args.imgsz)
    with tempfile.TemporaryDirectory() as tmp:
        for p2 in (False, True):
            name = f"{args.backbone}-n{' +P2' if p2 else ' P3-P5'}"
            model = KeypointDetector(DetectorConfig("n", args.backbone, p2=p2, num_classes=1)).eval()
            flops[name] = gflops(model, args.imgsz)
            model.fuse()
            path = Path(tmp) / f"n-p2-{p2}.onnx"
            export_onnx(model, path, args.imgsz)
            fns[f"{name}|torch"] = (lambda m: lambda: m.infer(x))(model)
            fns[f"{name}|ort"] = ort_runner(path, args.imgsz)
        for name, (file, gf) in ANCHOR_FILES.items():
            path = ANCHORS / file
            if not path.exists():
                print(f"anchor {path} missing: skipped")
                continue
            flops[name] = gf
            fns[f"{name}|ort"] = ort_runner(path, args.imgsz)
        # ONNX Runtime and PyTorch keep their worker threads spinning after each call: timed in
        # turn with each other they would steal each other's cores, so each runtime is timed apart
        ms = time_interleaved({k: f for k, f in fns.items() if k.endswith("|ort")}, args.warmup, args.repeats)
        with torch.inference_mode():
            ms.update(time_interleaved({k: f for k, f in fns.items() if k.endswith("|torch")},
                                       args.warmup, args.repeats))
    rows = [(name, gf, ms.get(f"{name}|torch"), ms[f"{name}|ort"]) for name, gf in flops.items()]

    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
          f"torch {torch.__version__}, onnxruntime {ort.__version__}")
    print(f"batch 1, {args.imgsz}x{args.imgsz}, median of {args.repeats} runs after {args.warmup} warm-ups, "
          f"2 threads, models of one runtime run in turn")
    print(f"{'model':32s} {'GFLOPs':>7s} {'PyTorch ms':>11s} {'ORT ms':>8s}")
    for name, flops, t_torch, t_ort in rows:
        tt = f"{t_torch:11.1f}" if t_torch is not None else f"{'-':>11s}"
        print(f"{name:32s} {flops:7.2f} {tt} {t_ort:8.1f}")
    ours = next(r[3] for r in rows if r[0].endswith("+P2"))
    ref = next((r[3] for r in rows if r[0].startswith("yolo11n-pose")), None)
    if ref is not None:
        ratio = ours / ref
        verdict = "met" if ratio <= TARGET_RATIO else "NOT met"
        print(f"ratio n+P2 (ORT) / yolo11n-pose (ORT): {ratio:.2f}x; target <= {TARGET_RATIO}x: {verdict}")


if __name__ == "__main__":
    main()
