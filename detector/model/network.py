"""The keypoint detector: backbone (by name) -> PAN neck -> decoupled head, configured by a plain
dataclass that checkpoints store as a dict.

Scales follow the published YOLO tables for each backbone family (depth multiple, width multiple,
channel cap): YOLOv8's for 'c2f', YOLO11's for 'c3k2'. Width/depth/max_channels can be overridden
to build tiny models for tests.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from omnigen.detector.model.backbones import BACKBONES, build_backbone
from omnigen.detector.model.blocks import fuse_batchnorm
from omnigen.detector.model.head import KeypointHead
from omnigen.detector.model.crop_stage import CropNet, SplitCropNet, crop_outputs
from omnigen.detector.model.neck import PAN
from omnigen.detector.model.outputs import KPT_MODES, REG_MAX, HeadOutput, decode
from omnigen.conventions import FINE_CLASSES

SCALE_NAMES = ("n", "s", "m", "l", "x")

SCALES: dict[str, dict[str, tuple[float, float, int]]] = {
    # YOLOv8 (ultralytics/cfg/models/v8/yolov8.yaml): depth, width, max_channels
    "c2f": {"n": (0.33, 0.25, 1024), "s": (0.33, 0.50, 1024), "m": (0.67, 0.75, 768),
            "l": (1.00, 1.00, 512), "x": (1.00, 1.25, 512)},
    # YOLO11 (ultralytics/cfg/models/11/yolo11.yaml)
    "c3k2": {"n": (0.50, 0.25, 1024), "s": (0.50, 0.50, 1024), "m": (0.50, 1.00, 512),
             "l": (1.00, 1.00, 512), "x": (1.00, 1.50, 512)},
}
"""(depth multiple, width multiple, max channels) per backbone family and scale."""

HEAVY_SCALES = ("m", "l", "x")
"""Scales that use the deeper C3k inner blocks everywhere (YOLO11's recipe)."""


@dataclass
class DetectorConfig:
    """Everything needed to rebuild a detector (stored in checkpoints via to_dict)."""

    scale: str = "n"
    backbone: str = "c3k2"
    p2: bool = True
    p6: bool = False
    num_classes: int = len(FINE_CLASSES)
    width: float | None = None  # overrides of the scale's multiples (tiny test models)
    depth: float | None = None
    max_channels: int | None = None
    reg_max: int = REG_MAX
    kpt_mode: str = "anchor"  # how corners decode: offsets from the anchor, or in units of the box (outputs.py)
    kpt_heading: bool = False  # corners up to the turn, the front read from a regressed image heading (heading.py)
    heading_crop: int = 0  # side of the crops a second stage places each object's corners and front from (crop_stage.py); 0: none
    crop_classes: bool = False  # the crop stage names each crop's class too, and prediction rescores by it (crop_stage.py)
    # those classes from a crop net of their own, not the corners' (crop_stage.SplitCropNet): the
    # stage the crop phase attaches (crop_train.attach_stage); training with the detector builds a CropNet
    crop_split: bool = False
    crop_position: bool = False  # the crop stage's corners' net is told where each crop was cut (crop_stage.crop_position)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if self.backbone not in BACKBONES:
            raise ValueError(f"DetectorConfig.backbone: unknown {self.backbone!r}; "
                             f"known backbones: {', '.join(sorted(BACKBONES))}")
        if self.scale not in SCALE_NAMES:
            raise ValueError(f"DetectorConfig.scale: {self.scale!r} is not one of {', '.join(SCALE_NAMES)}")
        if not isinstance(self.num_classes, int) or self.num_classes < 1:
            raise ValueError(f"DetectorConfig.num_classes: must be a positive integer, got {self.num_classes!r}")
        if self.width is not None and not self.width > 0:
            raise ValueError(f"DetectorConfig.width: must be > 0, got {self.width!r}")
        if self.depth is not None and not self.depth > 0:
            raise ValueError(f"DetectorConfig.depth: must be > 0, got {self.depth!r}")
        if self.max_channels is not None and self.max_channels < 8:
            raise ValueError(f"DetectorConfig.max_channels: must be >= 8, got {self.max_channels!r}")
        if self.kpt_mode not in KPT_MODES:
            raise ValueError(f"DetectorConfig.kpt_mode: {self.kpt_mode!r} is not one of {', '.join(KPT_MODES)}")
        if not isinstance(self.heading_crop, int) or self.heading_crop < 0 or self.heading_crop % 16:
            raise ValueError(f"DetectorConfig.heading_crop: must be 0 (none) or a positive multiple of 16 "
                             f"(the crop net halves it four times), got {self.heading_crop!r}")
        if self.crop_classes and not self.heading_crop:
            raise ValueError("DetectorConfig.crop_classes: needs the crop stage (heading_crop > 0)")
        if self.crop_split and not self.crop_classes:
            raise ValueError("DetectorConfig.crop_split: gives the crop stage's classes a net of their own; "
                             "needs crop_classes")
        if self.crop_position and not self.heading_crop:
            raise ValueError("DetectorConfig.crop_position: needs the crop stage (heading_crop > 0)")
        if self.reg_max != REG_MAX:
            raise ValueError(f"DetectorConfig.reg_max: decoding is built for {REG_MAX} bins, got {self.reg_max}")

    @property
    def multiples(self) -> tuple[float, float, int]:
        """(depth, width, max_channels) after overrides."""
        depth, width, max_channels = SCALES[self.backbone][self.scale]
        return (self.depth if self.depth is not None else depth,
                self.width if self.width is not None else width,
                self.max_channels if self.max_channels is not None else max_channels)

    @property
    def strides(self) -> list[int]:
        return ([4] if self.p2 else []) + [8, 16, 32] + ([64] if self.p6 else [])

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "DetectorConfig":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"DetectorConfig: unknown fields {unknown}; known: {sorted(known)}")
        return cls(**data)


class KeypointDetector(nn.Module):
    """Images (B, 3, H, W) in 0..1, H and W multiples of the largest stride -> HeadOutput."""

    def __init__(self, cfg: DetectorConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        depth, width, max_channels = cfg.multiples
        heavy = cfg.scale in HEAVY_SCALES
        self.strides: list[int] = cfg.strides
        self.backbone = build_backbone(cfg.backbone, width, depth, max_channels, cfg.p6, heavy)
        self.neck = PAN(self.backbone.channels, self.strides, cfg.backbone, width, depth, max_channels, heavy)
        chans = [self.neck.out_channels[s] for s in self.strides]
        self.head = KeypointHead(chans, self.strides, cfg.num_classes, self.neck.out_channels[8], cfg.reg_max,
                                 cfg.kpt_mode, cfg.kpt_heading)
        self.crop_net = None
        if cfg.crop_split:
            self.crop_net = SplitCropNet(cfg.heading_crop, cfg.num_classes, position=cfg.crop_position)
        elif cfg.heading_crop:
            self.crop_net = CropNet(cfg.heading_crop, num_classes=cfg.num_classes if cfg.crop_classes else 0,
                                    position=cfg.crop_position)

    def forward(self, images: torch.Tensor, crops: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
                ) -> HeadOutput:
        """`crops` (rows, batch index, xyxy boxes: (N,), (N,), (N, 4)) of a crop-stage model are cut
        from `images` and their headings returned in the output with the rows of the targets they
        stand for. Here in the forward, so that data parallelism sees the crop net's parameters used."""
        top = self.strides[-1]
        # not while traced (detector/prediction/export_onnx.py checks the fixed input first): the test would only warn
        if not torch.jit.is_tracing() and (images.shape[-1] % top or images.shape[-2] % top):
            raise ValueError(f"KeypointDetector: image size {tuple(images.shape[-2:])} is not a multiple "
                             f"of the largest stride {top}")
        out = self.head(self.neck(self.backbone(images)))
        if crops is not None:
            if self.crop_net is None:
                raise ValueError("KeypointDetector: crops given to a model without a crop stage "
                                 "(DetectorConfig.heading_crop is 0)")
            rows, batch_index, boxes = crops
            out.crop_heading, out.crop_corners, out.crop_logits = crop_outputs(
                self.crop_net, images, batch_index, boxes, self.cfg.heading_crop)
            out.crop_rows, out.crop_boxes = rows, boxes
        return out

    def infer(self, images: torch.Tensor) -> torch.Tensor:
        """Decoded predictions (B, 4 + nc + 24, A): the tensor that prediction and ONNX use."""
        return decode(self(images))

    def fuse(self) -> "KeypointDetector":
        """Fold batch-norms into convolutions for inference (eval mode only; not reversible)."""
        if self.training:
            raise RuntimeError("KeypointDetector.fuse: call model.eval() first")
        fuse_batchnorm(self)
        return self


class InferenceWrapper(nn.Module):
    """`model.infer` as a module's forward (what torch.onnx.export traces)."""

    def __init__(self, model: KeypointDetector):
        super().__init__()
        self.model = model
        # same mode as the model: torch.onnx.export restores the wrapper's mode afterwards, and a
        # wrapper left in training mode would switch the wrapped model back to training
        self.train(model.training)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.model.infer(images)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def gflops(model: nn.Module, imgsz: int = 640) -> float:
    """FLOPs of one forward pass on a (1, 3, imgsz, imgsz) input, / 1e9, as counted by
    torch.utils.flop_counter (2 FLOPs per multiply-accumulate of convolutions and matmuls: the
    convention of Ultralytics' thop-based GFLOPs). Counts only convolutions/matmuls, as they do."""
    # counted on a copy on the meta device: shapes only, no arithmetic, so even x at 640 is instant
    meta = copy.deepcopy(model).to("meta").eval()
    p = next(meta.parameters())
    x = torch.zeros(1, 3, imgsz, imgsz, device="meta", dtype=p.dtype)
    counter = FlopCounterMode(display=False)
    with counter, torch.no_grad():
        meta(x)
    return counter.get_total_flops() / 1e9
