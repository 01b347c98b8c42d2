"""benchmarks/bench_train_speed.py: each measurement runs (tiny, on the CPU) and prints its figures;
the throughput's loader timing counts only batches decoded after its clock started (issue 24)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("cv2", reason="opencv-python-headless is part of the train extra")

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks import bench_train_speed as bench  # noqa: E402

TINY = ["--width", "0.125", "--depth", "0.34"]


def test_throughput_prints_each_stage_and_ends_with_end_to_end():
    out = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_train_speed.py"), "throughput", "--device", "cpu", "--imgsz", "64",
         "--batch", "2", "--workers", "1", "--steps", "2", *TINY, "--frames", "4", "--fake-size", "160x96", "--threads", "1"],
        capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.strip().splitlines()
    for stage in ("loader, one process", "loader, 1 workers: total", "loader, per worker", "step alone", "end to end"):
        assert any(line.startswith(f"| {stage}") for line in lines), (stage, out.stdout)
    m = re.fullmatch(r"end-to-end: (\d+\.\d) img/s", lines[-1])
    assert m and float(m.group(1)) > 0, lines[-1]
    assert any(line.startswith("each loader measurement discarded its first 4 batches") for line in lines), out.stdout


def test_compare_workers_times_each_count_and_sets_them_against_the_first():
    out = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_train_speed.py"), "throughput", "--device", "cpu", "--imgsz", "64",
         "--batch", "2", "--workers", "0", "--steps", "2", *TINY, "--frames", "4", "--fake-size", "160x96", "--threads", "1",
         "--compare-workers", "0,1", "--rounds", "1"],
        capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = {m.group(1): (float(m.group(2)), float(m.group(3)))
            for m in re.finditer(r"^\| (\d+) \| (\d+\.\d) \| (\d+\.\d\d) \|$", out.stdout, re.M)}
    assert set(rows) == {"0", "1"} and rows["0"][1] == 1.0 and all(rate > 0 for rate, _ in rows.values()), out.stdout
    assert round(rows["1"][0] / rows["0"][0], 2) == pytest.approx(rows["1"][1], abs=0.011)


@pytest.mark.parametrize("text", ["0", "0,0", "1,-1", "a,b"])
def test_compare_workers_wants_two_distinct_counts(text):
    import argparse

    with pytest.raises(argparse.ArgumentTypeError):
        bench.worker_counts(text)
    assert bench.worker_counts("0,1,2") == [0, 1, 2]


def test_a_loader_measurement_times_only_batches_decoded_after_its_clock_started(monkeypatch):
    # Iterating a loader queues PREFETCH batches per worker at once; the timed batches must be the
    # ones after those, and the rate counts only them.
    import torch

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


def test_measurements_alternate_round_by_round_and_report_each_median():
    calls = []

    def measure(name, seconds):
        return lambda r: calls.append((r, name)) or seconds[r]
    med = bench.alternating_medians({"a": measure("a", [1.0, 5.0, 3.0]), "b": measure("b", [2.0, 2.0, 9.0])}, 3)
    assert calls == [(0, "a"), (0, "b"), (1, "a"), (1, "b"), (2, "a"), (2, "b")]
    assert med == {"a": 3.0, "b": 2.0}


def test_step_prints_both_precisions_and_their_ratio(capsys):
    assert bench.main(["step", "--imgsz", "64", "--batch", "2", "--steps", "1", "--threads", "1", *TINY]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert any(line.startswith("| float32 | ") for line in lines) and any(line.startswith("| bf16 | ") for line in lines)
    assert re.fullmatch(r"bf16 / float32 step time: \d+\.\d\d", lines[-1]), lines[-1]


def test_the_loop_times_the_trainings_own_step_contiguous_and_channels_last(capsys):
    assert bench.main(["step", "--loop", "--imgsz", "64", "--batch", "2", "--steps", "1", "--threads", "1", *TINY]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(("| contiguous |", "| channels-last |"))]
    assert len(rows) == 2 and rows[0].endswith("| 1.000 |") and float(rows[1].split("|")[2]) > 0


def test_cache_times_the_loader_from_disk_and_from_memory(tmp_path, capsys):
    from omnigen.fakes import write_fake_dataset

    ds = write_fake_dataset(tmp_path / "uov", 4, objects_per_frame=3, seed=1)
    assert bench.main(["cache", str(ds.root), "--imgsz", "64", "--crop", "0", "--workers", "0", "--batch", "2",
                       "--epochs", "1"]) == 0
    out = capsys.readouterr().out
    for row in ("images from disk", "images in memory (--cache)", "ratio memory / disk", "memory held (MiB)"):
        assert row in out, out


def test_a_folder_without_a_dataset_is_refused_in_one_line(tmp_path):
    with pytest.raises(SystemExit, match=r"manifest\.json: not a dataset"):
        bench.main(["cache", str(tmp_path)])
