"""Parameters (millions) and GFLOPs at 640 of the detector for every scale, backbone family and
level option (P3-P5, +P2 the default, +P2+P6), one class. Runs once; no timing.

GFLOPs are FLOPs / 1e9 of one 1x3x640x640 forward pass as counted by torch.utils.flop_counter
(2 FLOPs per multiply-accumulate of convolutions and matrix products), the convention of
Ultralytics' published GFLOPs (thop MACs x 2). Reference: YOLO11n-pose with 8 keypoints and one
class, 2.70 M parameters and 6.9 GFLOPs (/work/shared/anchors/README.md).

    .venv/bin/python benchmarks/bench_detector_size.py
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.detector.model.backbones import BACKBONES  # noqa: E402
from omnigen.detector.model.network import SCALE_NAMES, DetectorConfig, KeypointDetector, count_parameters, gflops  # noqa: E402

LEVELS = {"P3-P5": (False, False), "+P2": (True, False), "+P2+P6": (True, True)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--imgsz", type=int, default=640)
    ap.add_argument("--scales", default="".join(SCALE_NAMES))
    args = ap.parse_args()
    torch.set_num_threads(2)

    header = "| backbone | scale | " + " | ".join(f"{k} params (M) | {k} GFLOPs" for k in LEVELS) + " |"
    print(f"one class, input {args.imgsz}x{args.imgsz}")
    print(header)
    print("|" + "---|" * (2 + 2 * len(LEVELS)))
    for backbone in sorted(BACKBONES):
        for scale in args.scales:
            cells = []
            for p2, p6 in LEVELS.values():
                model = KeypointDetector(DetectorConfig(scale, backbone, p2=p2, p6=p6, num_classes=1))
                cells += [f"{count_parameters(model) / 1e6:.2f}", f"{gflops(model, args.imgsz):.1f}"]
            print(f"| {backbone} | {scale} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
