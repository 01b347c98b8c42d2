"""Convolutional building blocks of the detector (YOLOv8 / YOLO11 families), written from their
published descriptions in plain PyTorch.

Every block keeps the tensor layout (B, C, H, W) and only changes channels (and, for strided
convolutions, the resolution). Batch-norm uses the momentum and epsilon of the YOLO family
(0.03, 1e-3): these are what their training recipes (and so ours) were tuned with.
"""

from __future__ import annotations

import torch
from torch import nn

BN_EPS = 1e-3
BN_MOMENTUM = 0.03


class Conv(nn.Module):
    """Conv2d (no bias) + BatchNorm + SiLU: the unit every other block is made of.

    `fuse()` folds the batch-norm into the convolution for inference (same outputs, fewer ops)."""

    def __init__(self, c_in: int, c_out: int, k: int = 1, s: int = 1, groups: int = 1, act: bool = True):
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, k, s, k // 2, groups=groups, bias=False)
        self.bn: nn.Module = nn.BatchNorm2d(c_out, eps=BN_EPS, momentum=BN_MOMENTUM)
        self.act: nn.Module = nn.SiLU() if act else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(self.conv(x)))

    @torch.no_grad()
    def fuse(self) -> None:
        """Fold the batch-norm statistics into the convolution weights (inference only)."""
        if not isinstance(self.bn, nn.BatchNorm2d):
            return
        bn = self.bn
        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        fused = nn.Conv2d(self.conv.in_channels, self.conv.out_channels, self.conv.kernel_size,
                          self.conv.stride, self.conv.padding, groups=self.conv.groups, bias=True)
        fused.weight.copy_(self.conv.weight * scale.view(-1, 1, 1, 1))
        fused.bias.copy_(bn.bias - bn.running_mean * scale)
        self.conv = fused.to(self.conv.weight.device)
        self.bn = nn.Identity()


class DWConv(Conv):
    """Depthwise convolution (one filter per channel; c_out a multiple of c_in)."""

    def __init__(self, c_in: int, c_out: int, k: int = 3, s: int = 1, act: bool = True):
        super().__init__(c_in, c_out, k, s, groups=c_in, act=act)


class DSConv(nn.Sequential):
    """Depthwise-separable convolution: depthwise k x k then pointwise 1 x 1.

    About k*k times cheaper than a full convolution of the same width: what keeps the heads of the
    stride-4 level (160 x 160 cells at 640) affordable on a CPU."""

    def __init__(self, c_in: int, c_out: int, k: int = 3):
        super().__init__(DWConv(c_in, c_in, k), Conv(c_in, c_out, 1))


class Bottleneck(nn.Module):
    """Two convolutions with an optional residual connection (when shapes allow it)."""

    def __init__(self, c_in: int, c_out: int, shortcut: bool = True, k: tuple[int, int] = (3, 3),
                 e: float = 0.5):
        super().__init__()
        hidden = int(c_out * e)
        self.cv1 = Conv(c_in, hidden, k[0])
        self.cv2 = Conv(hidden, c_out, k[1])
        self.add = shortcut and c_in == c_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.cv2(self.cv1(x))
        return x + y if self.add else y


class C2f(nn.Module):
    """Cross-stage partial block with two convolutions (YOLOv8): split, run n bottlenecks on one
    half, concatenate every intermediate output, fuse with a 1 x 1 convolution."""

    def __init__(self, c_in: int, c_out: int, n: int = 1, shortcut: bool = False, e: float = 0.5):
        super().__init__()
        self.c = int(c_out * e)
        self.cv1 = Conv(c_in, 2 * self.c, 1)
        self.cv2 = Conv((2 + n) * self.c, c_out, 1)
        self.m = nn.ModuleList(self._inner(shortcut) for _ in range(n))

    def _inner(self, shortcut: bool) -> nn.Module:
        return Bottleneck(self.c, self.c, shortcut, (3, 3), e=1.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        ys = list(self.cv1(x).chunk(2, 1))
        for m in self.m:
            ys.append(m(ys[-1]))
        return self.cv2(torch.cat(ys, 1))


class C3k(nn.Module):
    """CSP block with three convolutions and k x k bottlenecks (the inner block of C3k2)."""

    def __init__(self, c_in: int, c_out: int, n: int = 2, shortcut: bool = True, e: float = 0.5, k: int = 3):
        super().__init__()
        hidden = int(c_out * e)
        self.cv1 = Conv(c_in, hidden, 1)
        self.cv2 = Conv(c_in, hidden, 1)
        self.cv3 = Conv(2 * hidden, c_out, 1)
        self.m = nn.Sequential(*(Bottleneck(hidden, hidden, shortcut, (k, k), e=1.0) for _ in range(n)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.cv3(torch.cat([self.m(self.cv1(x)), self.cv2(x)], 1))


class C3k2(C2f):
    """C2f whose inner blocks are either plain bottlenecks or C3k blocks (YOLO11). `c3k=True` is the
    heavier, deeper variant used for the coarse levels and the larger scales."""

    def __init__(self, c_in: int, c_out: int, n: int = 1, c3k: bool = False, e: float = 0.5,
                 shortcut: bool = True):
        self._c3k = c3k
        super().__init__(c_in, c_out, n, shortcut, e)

    def _inner(self, shortcut: bool) -> nn.Module:
        if self._c3k:
            return C3k(self.c, self.c, 2, shortcut)
        return Bottleneck(self.c, self.c, shortcut, (3, 3), e=0.5)


class SPPF(nn.Module):
    """Spatial pyramid pooling, fast: three chained 5 x 5 max-pools (receptive fields 5, 9, 13)
    concatenated, widening the context of the coarsest level for the cost of a few pools."""

    def __init__(self, c_in: int, c_out: int, k: int = 5):
        super().__init__()
        hidden = c_in // 2
        self.cv1 = Conv(c_in, hidden, 1)
        self.cv2 = Conv(hidden * 4, c_out, 1)
        self.pool = nn.MaxPool2d(k, 1, k // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        ys = [self.cv1(x)]
        for _ in range(3):
            ys.append(self.pool(ys[-1]))
        return self.cv2(torch.cat(ys, 1))


class Attention(nn.Module):
    """Multi-head self-attention over the cells of a (small, coarse) feature map, with a depthwise
    positional convolution on the values (no explicit position embedding: any input size works)."""

    def __init__(self, dim: int, num_heads: int, attn_ratio: float = 0.5):
        super().__init__()
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.key_dim = int(self.head_dim * attn_ratio)
        self.scale = self.key_dim ** -0.5
        self.qkv = Conv(dim, dim + 2 * self.key_dim * num_heads, 1, act=False)
        self.proj = Conv(dim, dim, 1, act=False)
        # a plain depthwise conv: a bias (or batch-norm shift) here would be a per-channel constant
        # that the batch-norm of `proj` removes again, a parameter that never learns
        self.pe = nn.Conv2d(dim, dim, 3, 1, 1, groups=dim, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        qkv = self.qkv(x).view(b, self.num_heads, 2 * self.key_dim + self.head_dim, h * w)
        q, k, v = qkv.split([self.key_dim, self.key_dim, self.head_dim], dim=2)
        attn = ((q.transpose(-2, -1) @ k) * self.scale).softmax(-1)  # (b, heads, N, N)
        y = (v @ attn.transpose(-2, -1)).view(b, c, h, w) + self.pe(v.reshape(b, c, h, w))
        return self.proj(y)


class PSABlock(nn.Module):
    """Attention then a two-layer feed-forward, each with a residual connection."""

    def __init__(self, c: int, num_heads: int):
        super().__init__()
        self.attn = Attention(c, num_heads)
        self.ffn = nn.Sequential(Conv(c, 2 * c, 1), Conv(2 * c, c, 1, act=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(x)
        return x + self.ffn(x)


class C2PSA(nn.Module):
    """CSP wrapper around n PSA blocks (YOLO11, after SPPF): attention on half the channels of the
    coarsest level, where the map is small (20 x 20 at 640) and global context is cheap."""

    def __init__(self, c_in: int, n: int = 1, e: float = 0.5):
        super().__init__()
        self.c = int(c_in * e)
        self.cv1 = Conv(c_in, 2 * self.c, 1)
        self.cv2 = Conv(2 * self.c, c_in, 1)
        heads = max(1, self.c // 64)
        self.m = nn.Sequential(*(PSABlock(self.c, heads) for _ in range(n)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a, b = self.cv1(x).split((self.c, self.c), dim=1)
        return self.cv2(torch.cat([a, self.m(b)], 1))


def fuse_batchnorm(model: nn.Module) -> nn.Module:
    """Fold every Conv's batch-norm into its convolution, in place (inference speed); returns model."""
    for m in model.modules():
        if isinstance(m, Conv):
            m.fuse()
    return model
