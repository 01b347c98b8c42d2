"""What the crop net's pooling costs at prediction: PyTorch's max_pool2d against crop_stage.MaxPool2.

    .venv/bin/python benchmarks/bench_crop_pool.py [--rounds 15] [--batch 128] [--side 64] [--threads 0]

Why: a profile of make validate's prediction showed the crop nets' 2 x 2 max pools next to their
convolutions in time. crop_stage.MaxPool2 takes, in eval mode, the maximum of column pairs and
then of row pairs, the same values as max_pool2d. This script times both, in one run with the
two alternating round by round so that a busy machine slows both alike:

- the pool alone on each block's map of a crop net of side `--side` (a batch of `--batch` crops,
  the chunk prediction runs): 16 channels at the side, 32 at half, 64 at a quarter and an eighth;
- a whole CropNet forward (eval mode) with its pools as max_pool2d and as MaxPool2.

It checks that the two give the same values. Prints medians in milliseconds and their ratios; last
line `crop_pool: whole net max_pool2d X ms, MaxPool2 Y ms (ratio R)`.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.detector.crop_stage import CropNet, MaxPool2  # noqa: E402


class KernelPool(nn.Module):
    """max_pool2d in every mode: what the crop net's pools were."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.max_pool2d(x, 2)


def with_pools(net: CropNet, pool: type[nn.Module]) -> CropNet:
    """`net` with each MaxPool2 replaced by `pool()` (in place; no tensors change)."""
    for block in net.features:
        if isinstance(block, nn.Sequential):
            for i, m in enumerate(block):
                if isinstance(m, (MaxPool2, KernelPool)):
                    block[i] = pool().train(net.training)  # a new module starts in training mode
    return net


def timed(fn, rounds: int) -> list[float]:
    fn()  # warm up
    out = []
    for _ in range(rounds):
        t = time.perf_counter()
        fn()
        out.append(1000 * (time.perf_counter() - t))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--batch", type=int, default=128, help="crops a forward (crop_stage.refine's chunk)")
    ap.add_argument("--side", type=int, default=64, help="crop side (a multiple of 16)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    a = ap.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    shapes = [(16, a.side), (32, a.side // 2), (64, a.side // 4), (64, a.side // 8)]
    maps = [torch.randn(a.batch, c, s, s) for c, s in shapes]
    fast, kernel = MaxPool2().eval(), KernelPool()
    for x in maps:
        if not torch.equal(fast(x), kernel(x)):
            raise SystemExit("crop_pool: MaxPool2 and max_pool2d differ")
    net = CropNet(a.side, num_classes=12).eval()
    crops = torch.rand(a.batch, 3, a.side, a.side)
    times: dict[str, list[float]] = {}
    with torch.inference_mode():
        new = net(crops)
        old = with_pools(net, KernelPool)(crops)
        with_pools(net, MaxPool2)
        if not torch.equal(new, old):
            raise SystemExit("crop_pool: the net's outputs differ between the two pools")
        for _ in range(a.rounds):  # alternate, one round of each at a time
            for (c, s), x in zip(shapes, maps):
                times.setdefault(f"pool {c} x {s} x {s}, max_pool2d", []).extend(timed(lambda: kernel(x), 1))
                times.setdefault(f"pool {c} x {s} x {s}, MaxPool2", []).extend(timed(lambda: fast(x), 1))
            with_pools(net, KernelPool)
            times.setdefault("whole net, max_pool2d", []).extend(timed(lambda: net(crops), 1))
            with_pools(net, MaxPool2)
            times.setdefault("whole net, MaxPool2", []).extend(timed(lambda: net(crops), 1))
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"crop net pooling, {a.batch} crops of {a.side} px, {torch.get_num_threads()} threads, "
          f"median of {a.rounds} rounds (ms):")
    print("| what | max_pool2d | MaxPool2 | ratio |")
    print("|---|---|---|---|")
    for c, s in shapes:
        k, f = med[f"pool {c} x {s} x {s}, max_pool2d"], med[f"pool {c} x {s} x {s}, MaxPool2"]
        print(f"| pool {c} x {s} x {s} | {k:.2f} | {f:.2f} | {k / f:.2f} |")
    k, f = med["whole net, max_pool2d"], med["whole net, MaxPool2"]
    print(f"| whole net | {k:.2f} | {f:.2f} | {k / f:.2f} |")
    print(f"crop_pool: whole net max_pool2d {k:.1f} ms, MaxPool2 {f:.1f} ms (ratio {k / f:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
