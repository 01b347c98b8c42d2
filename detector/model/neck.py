"""PAN neck: a top-down pass (coarse context into fine levels) then a bottom-up pass (fine detail
back into coarse levels), over the levels the head predicts on.

Levels are strides: P3-P5 (8, 16, 32) always, P2 (4) on by default for small, distant objects,
P6 (64) optionally for very large ones. The top-down pass starts at the coarsest backbone feature
and ends at the finest level; the bottom-up pass climbs back with strided convolutions.

The stride-4 level costs 4x the cells of stride 8, so its blocks are the narrowest (nominal 128
channels, 32 at scale n); with the depthwise-separable head this keeps n with P2 near the cost of
YOLO11n-pose (see docs/detector-model.md).
"""

from __future__ import annotations

import torch
from torch import nn

from omnigen.detector.model.backbones import scale_channels, scale_depth
from omnigen.detector.model.blocks import C2f, C3k2, Conv

NECK_CHANNELS = {4: 128, 8: 256, 16: 512, 32: 1024, 64: 1024}
"""Nominal output channels of the neck per stride, before width scaling."""


class PAN(nn.Module):
    """Path-aggregation neck over `levels` (strides, finest first) of a backbone whose feature
    channels per stride are `in_channels`. `out_channels[stride]` gives the head's input widths."""

    def __init__(self, in_channels: dict[int, int], levels: list[int], family: str, width: float,
                 depth: float, max_channels: int, heavy: bool = False):
        super().__init__()
        levels = sorted(levels)
        missing = [s for s in levels if s not in in_channels]
        if missing:
            raise ValueError(f"PAN levels {missing} not produced by the backbone (strides {sorted(in_channels)})")
        self.levels = levels
        top = levels[-1]
        c = {s: scale_channels(NECK_CHANNELS[s], width, max_channels) for s in levels}

        def block(c_in: int, c_out: int, stride: int) -> nn.Module:
            if family == "c2f":
                return C2f(c_in, c_out, scale_depth(3, depth), shortcut=False)
            return C3k2(c_in, c_out, scale_depth(2, depth), c3k=heavy or stride == top)

        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        # top-down: for each level below the top, fuse the upsampled coarser map with the backbone's
        self.td = nn.ModuleDict()
        coarser = in_channels[top]
        for s in reversed(levels[:-1]):
            self.td[str(s)] = block(coarser + in_channels[s], c[s], s)
            coarser = c[s]
        # bottom-up: a strided conv from the finer output, fused with that level's top-down map
        self.down = nn.ModuleDict()
        self.bu = nn.ModuleDict()
        for finer, s in zip(levels[:-1], levels[1:]):
            lateral = in_channels[top] if s == top else c[s]
            self.down[str(s)] = Conv(c[finer], c[finer], 3, 2)
            self.bu[str(s)] = block(c[finer] + lateral, c[s], s)
        self.out_channels = c

    def forward(self, feats: dict[int, torch.Tensor]) -> list[torch.Tensor]:
        top = self.levels[-1]
        td = {top: feats[top]}
        x = feats[top]
        for s in reversed(self.levels[:-1]):
            x = self.td[str(s)](torch.cat([self.up(x), feats[s]], 1))
            td[s] = x
        outs = [x]
        for s in self.levels[1:]:
            x = self.bu[str(s)](torch.cat([self.down[str(s)](x), td[s]], 1))
            outs.append(x)
        return outs
