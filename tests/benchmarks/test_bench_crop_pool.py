"""benchmarks/bench_crop_pool.py runs, checks the two pools agree and prints its last line."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import bench_crop_pool  # noqa: E402
from omnigen.detector.crop_stage import CropNet, MaxPool2  # noqa: E402


def test_the_benchmark_swaps_the_pools_in_their_mode_and_prints_its_figures(capsys):
    net = CropNet(16).eval()
    def pools() -> list:
        return [m for block in net.features if hasattr(block, "__iter__") for m in block
                if isinstance(m, (MaxPool2, bench_crop_pool.KernelPool))]

    bench_crop_pool.with_pools(net, bench_crop_pool.KernelPool)
    assert len(pools()) == 4 and all(isinstance(m, bench_crop_pool.KernelPool) and not m.training for m in pools())
    bench_crop_pool.with_pools(net, MaxPool2)  # and back: four of them, in the net's mode
    assert len(pools()) == 4 and all(isinstance(m, MaxPool2) and not m.training for m in pools())
    assert bench_crop_pool.main(["--rounds", "1", "--batch", "2", "--side", "16"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith("crop_pool: whole net max_pool2d ")
