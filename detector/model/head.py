"""Anchor-free decoupled head: for every cell of every level, box (DFL logits), class logits and
keypoints (x, y offset and visibility logit per corner), each from its own branch.

Branches are built from depthwise-separable convolutions (like YOLO11's class branch) rather than
full 3 x 3 convolutions: the stride-4 level has 25,600 cells at 640, and full convolutions there
would double the cost of the n model. Every level has its own weights (as in YOLOv8/11); the
branch widths are the same for all levels, fixed by the stride-8 width.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from omnigen.detector.model.blocks import DSConv
from omnigen.detector.model.heading import HEADING_CHANNELS
from omnigen.detector.model.outputs import KPT_MODES, REG_MAX, HeadOutput, make_anchors
from omnigen.conventions import NUM_KEYPOINTS

KPT_OUTPUTS = NUM_KEYPOINTS * 3


LIGHT_STRIDES = (4,)
"""Levels whose branches have one depthwise-separable convolution instead of two: stride 4 has 4x
the cells of stride 8, and its objects are small, so a smaller receptive field in the head suffices."""


def _branch(c_in: int, hidden: int, c_out: int, light: bool = False) -> nn.Sequential:
    if light:
        return nn.Sequential(DSConv(c_in, hidden), nn.Conv2d(hidden, c_out, 1))
    return nn.Sequential(DSConv(c_in, hidden), DSConv(hidden, hidden), nn.Conv2d(hidden, c_out, 1))


class KeypointHead(nn.Module):
    """Per-level box / class / keypoint branches over the neck outputs (finest level first)."""

    def __init__(self, in_channels: list[int], strides: list[int], num_classes: int, ref_channels: int,
                 reg_max: int = REG_MAX, kpt_mode: str = "anchor", kpt_heading: bool = False):
        super().__init__()
        if len(in_channels) != len(strides):
            raise ValueError(f"head: {len(in_channels)} input levels but {len(strides)} strides")
        if kpt_mode not in KPT_MODES:
            raise ValueError(f"head: kpt_mode {kpt_mode!r} is not one of {', '.join(KPT_MODES)}")
        self.kpt_mode = kpt_mode
        self.kpt_heading = kpt_heading
        self.num_classes = num_classes
        self.reg_max = reg_max
        self.strides = list(strides)
        c_box = max(16, ref_channels // 4, 4 * reg_max)
        c_cls = max(ref_channels, min(num_classes, 100))
        c_kpt = max(ref_channels // 4, KPT_OUTPUTS)  # Ultralytics' pose head width
        light = [s in LIGHT_STRIDES for s in strides]
        self.box = nn.ModuleList(_branch(c, c_box, 4 * reg_max, lt) for c, lt in zip(in_channels, light))
        self.cls = nn.ModuleList(_branch(c, c_cls, num_classes, lt) for c, lt in zip(in_channels, light))
        # a heading-aware head adds three channels to the keypoint branch: the direction of the
        # object's image heading (heading.py)
        self.kpt_channels = KPT_OUTPUTS + HEADING_CHANNELS * int(kpt_heading)
        self.kpt = nn.ModuleList(_branch(c, c_kpt, self.kpt_channels, lt) for c, lt in zip(in_channels, light))
        self.reset_bias()

    @torch.no_grad()
    def reset_bias(self, imgsz: int = 640) -> None:
        """Box logits start flat (bias 1.0); class logits start at a prior of about 5 objects per
        `imgsz` image spread over the level's cells, so early training is not swamped by negatives."""
        for box, cls, s in zip(self.box, self.cls, self.strides):
            box[-1].bias.fill_(1.0)
            cls[-1].bias.fill_(math.log(5 / self.num_classes / (imgsz / s) ** 2))

    def forward(self, feats: list[torch.Tensor]) -> HeadOutput:
        b = feats[0].shape[0]
        box = torch.cat([m(x).view(b, 4 * self.reg_max, -1) for m, x in zip(self.box, feats)], 2)
        cls = torch.cat([m(x).view(b, self.num_classes, -1) for m, x in zip(self.cls, feats)], 2)
        kpt = torch.cat([m(x).view(b, self.kpt_channels, -1) for m, x in zip(self.kpt, feats)], 2)
        heading = kpt[:, KPT_OUTPUTS:KPT_OUTPUTS + HEADING_CHANNELS] if self.kpt_heading else None
        shapes = [(x.shape[2], x.shape[3]) for x in feats]
        anchors, strides = make_anchors(shapes, self.strides, device=box.device, dtype=box.dtype)
        return HeadOutput(box=box, cls=cls, kpt=kpt[:, :KPT_OUTPUTS], anchors=anchors, strides=strides,
                          kpt_mode=self.kpt_mode, heading=heading)
