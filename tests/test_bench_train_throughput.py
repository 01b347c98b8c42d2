"""Issue 24 part 2: benchmarks/bench_train_throughput.py runs (tiny, on the CPU) and ends with its figure."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("cv2", reason="opencv-python-headless is part of the train extra")

ROOT = Path(__file__).resolve().parents[1]


def test_throughput_benchmark_prints_each_stage_and_ends_with_end_to_end():
    out = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_train_throughput.py"), "--device", "cpu", "--imgsz", "64",
         "--batch", "2", "--workers", "1", "--steps", "2", "--width", "0.125", "--depth", "0.34", "--frames", "4",
         "--fake-size", "160x96", "--threads", "1"],
        capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.strip().splitlines()
    for stage in ("loader, one process", "loader, 1 workers: total", "loader, per worker", "step alone", "end to end"):
        assert any(line.startswith(f"| {stage}") for line in lines), (stage, out.stdout)
    m = re.fullmatch(r"end-to-end: (\d+\.\d) img/s", lines[-1])
    assert m and float(m.group(1)) > 0, lines[-1]
