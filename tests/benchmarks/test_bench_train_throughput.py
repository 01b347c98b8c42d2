"""Issue 24 part 2: benchmarks/bench_train_throughput.py runs (tiny, on the CPU) and ends with its figure."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("cv2", reason="opencv-python-headless is part of the train extra")

ROOT = Path(__file__).resolve().parents[2]


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
    assert any(line.startswith("each loader measurement discarded its first 4 batches") for line in lines), out.stdout


def test_a_loader_measurement_times_only_batches_decoded_after_its_clock_started(monkeypatch):
    # Iterating a loader queues PREFETCH batches per worker at once; the timed batches must be the
    # ones after those, and the rate counts only them.
    import importlib.util

    import torch

    spec = importlib.util.spec_from_file_location("bench_train_throughput",
                                                  ROOT / "benchmarks" / "bench_train_throughput.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    served, used = [], []

    def stream():
        for k in range(100):
            served.append(k)
            yield torch.zeros(3 if k < 8 else 2, 1), {"k": k}, None
    now = [0.0]
    monkeypatch.setattr(bench.time, "perf_counter", lambda: now[0])

    def use(images, targets):
        used.append(targets["k"])
        now[0] += 1.0
    rate = bench.timed_rate(stream(), 8, 5, torch.device("cpu"), use)
    assert used == [8, 9, 10, 11, 12] and served == list(range(13))
    assert rate == 2 * 5 / 5.0  # the 5 timed batches of 2 images in 5 s; none of the discarded 3-image ones
