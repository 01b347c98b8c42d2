"""Pluggable backbones, chosen by name: each maps images to features at strides 4, 8, 16, 32
(and 64 when asked), so the neck and head never depend on which family produced them.

Families:
- 'c2f': YOLOv8-style, stages of C2f blocks with residual bottlenecks, SPPF on the coarsest level.
- 'c3k2': YOLO11-style, stages of C3k2 blocks (C3k inner blocks on the coarse stages and on the
  larger scales), SPPF then C2PSA attention on the coarsest level.

Channels are the nominal YOLO widths (64, 128, 256, 512, 1024) scaled by `width`, capped at
`max_channels`, rounded to multiples of 8; block repeats are scaled by `depth`.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import nn

from omnigen.detector.model.blocks import C2PSA, SPPF, C2f, C3k2, Conv


def scale_channels(c: int, width: float, max_channels: int) -> int:
    """Nominal channel count -> scaled, capped, rounded up to a multiple of 8."""
    return max(8, int(math.ceil(min(c, max_channels) * width / 8) * 8))


def scale_depth(n: int, depth: float) -> int:
    """Nominal repeat count -> scaled (at least one)."""
    return max(round(n * depth), 1)


class Backbone(nn.Module):
    """A stem and a list of stages; stage i outputs stride 2 ** (i + 2) (4, 8, 16, 32[, 64]).

    `channels[stride]` is the channel count of the feature at that stride."""

    def __init__(self, stem: nn.Module, stages: list[nn.Module], channels: dict[int, int]):
        super().__init__()
        self.stem = stem
        self.stages = nn.ModuleList(stages)
        self.channels = channels
        self.strides = sorted(channels)

    def forward(self, x: torch.Tensor) -> dict[int, torch.Tensor]:
        x = self.stem(x)
        feats = {}
        for stride, stage in zip(self.strides, self.stages):
            x = stage(x)
            feats[stride] = x
        return feats


def _c2f_backbone(width: float, depth: float, max_channels: int, p6: bool, heavy: bool) -> Backbone:
    c = lambda n: scale_channels(n, width, max_channels)  # noqa: E731
    d = lambda n: scale_depth(n, depth)  # noqa: E731
    stem = Conv(3, c(64), 3, 2)
    stages: list[nn.Module] = [
        nn.Sequential(Conv(c(64), c(128), 3, 2), C2f(c(128), c(128), d(3), shortcut=True)),
        nn.Sequential(Conv(c(128), c(256), 3, 2), C2f(c(256), c(256), d(6), shortcut=True)),
        nn.Sequential(Conv(c(256), c(512), 3, 2), C2f(c(512), c(512), d(6), shortcut=True)),
    ]
    channels = {4: c(128), 8: c(256), 16: c(512)}
    if p6:
        stages.append(nn.Sequential(Conv(c(512), c(1024), 3, 2), C2f(c(1024), c(1024), d(3), shortcut=True)))
        stages.append(nn.Sequential(Conv(c(1024), c(1024), 3, 2), C2f(c(1024), c(1024), d(3), shortcut=True),
                                    SPPF(c(1024), c(1024))))
        channels.update({32: c(1024), 64: c(1024)})
    else:
        stages.append(nn.Sequential(Conv(c(512), c(1024), 3, 2), C2f(c(1024), c(1024), d(3), shortcut=True),
                                    SPPF(c(1024), c(1024))))
        channels[32] = c(1024)
    return Backbone(stem, stages, channels)


def _c3k2_backbone(width: float, depth: float, max_channels: int, p6: bool, heavy: bool) -> Backbone:
    c = lambda n: scale_channels(n, width, max_channels)  # noqa: E731
    d = lambda n: scale_depth(n, depth)  # noqa: E731
    stem = Conv(3, c(64), 3, 2)
    stages: list[nn.Module] = [
        nn.Sequential(Conv(c(64), c(128), 3, 2), C3k2(c(128), c(256), d(2), c3k=heavy, e=0.25)),
        nn.Sequential(Conv(c(256), c(256), 3, 2), C3k2(c(256), c(512), d(2), c3k=heavy, e=0.25)),
        nn.Sequential(Conv(c(512), c(512), 3, 2), C3k2(c(512), c(512), d(2), c3k=True)),
    ]
    channels = {4: c(256), 8: c(512), 16: c(512)}
    top = [SPPF(c(1024), c(1024)), C2PSA(c(1024), d(2))]
    if p6:
        stages.append(nn.Sequential(Conv(c(512), c(1024), 3, 2), C3k2(c(1024), c(1024), d(2), c3k=True)))
        stages.append(nn.Sequential(Conv(c(1024), c(1024), 3, 2), C3k2(c(1024), c(1024), d(2), c3k=True), *top))
        channels.update({32: c(1024), 64: c(1024)})
    else:
        stages.append(nn.Sequential(Conv(c(512), c(1024), 3, 2), C3k2(c(1024), c(1024), d(2), c3k=True), *top))
        channels[32] = c(1024)
    return Backbone(stem, stages, channels)


BackboneFactory = Callable[[float, float, int, bool, bool], Backbone]

BACKBONES: dict[str, BackboneFactory] = {
    "c2f": _c2f_backbone,
    "c3k2": _c3k2_backbone,
}
"""Registry of backbone families by name: factory(width, depth, max_channels, p6, heavy)."""


def build_backbone(name: str, width: float, depth: float, max_channels: int, p6: bool = False,
                   heavy: bool = False) -> Backbone:
    """The backbone `name` at the given scale. `heavy` selects the deeper inner blocks that the
    YOLO11 recipe uses for the m, l and x scales (ignored by families without such a choice)."""
    if name not in BACKBONES:
        raise ValueError(f"unknown backbone {name!r}; known backbones: {', '.join(sorted(BACKBONES))}")
    return BACKBONES[name](width, depth, max_channels, p6, heavy)
