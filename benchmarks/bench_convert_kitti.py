"""How fast `omnigen convert kitti` turns a training-split-sized tree into a dataset.

Generates a KITTI-format tree of 7,481 frames (the training split's size) with tiny images
(omnigen.converters.kitti_fixture, about 5 objects and 1 DontCare a frame, like KITTI), then converts it
with hard links, exactly as the command does, into a fresh folder each run. Prints seconds, frames
per second and CPU seconds (this process and its workers) per run, then the median and the best
run. CPU seconds do not depend on what else runs on the machine; wall time does (compare the load
average). The target (issue 3): under 15 s on 2 cores.

    .venv/bin/python benchmarks/bench_convert_kitti.py [--frames 7481] [--runs 3] [--workers N]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import sys
import tempfile
import time
from contextlib import redirect_stdout
from io import StringIO
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.converters.common import default_workers  # noqa: E402
from omnigen.converters.kitti_fixture import write_kitti_tree  # noqa: E402
from omnigen.cli import main as omnigen  # noqa: E402


def cpu_seconds() -> float:
    """User + system CPU of this process and its finished children (the forked workers)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def convert_once(src: Path, out: Path, workers: int) -> tuple[float, float, str]:
    """Wall seconds and CPU seconds of one `omnigen convert kitti` run (finalize included), and
    its output. CPU time shows what the run costs when other work shares the machine."""
    captured = StringIO()
    cpu = cpu_seconds()
    start = time.perf_counter()
    with redirect_stdout(captured):
        code = omnigen(["convert", "kitti", str(src), "--out", str(out), "--link", "hardlink",
                        "--workers", str(workers)])
    seconds = time.perf_counter() - start
    if code != 0:
        raise SystemExit(f"conversion failed (exit {code}):\n{captured.getvalue()}")
    return seconds, cpu_seconds() - cpu, captured.getvalue()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=7481)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--workers", type=int, default=default_workers())
    args = p.parse_args()
    cpus = len(os.sched_getaffinity(0))
    with tempfile.TemporaryDirectory(prefix="bench-kitti-") as tmp:
        tmp_path = Path(tmp)
        start = time.perf_counter()
        write_kitti_tree(tmp_path / "kitti", args.frames, seed=0)
        os.sync()  # the conversion flushes once before its manifest: don't charge it the generator's writes
        print(f"generated {args.frames} frames in {time.perf_counter() - start:.1f} s")
        times, cpu_times = [], []
        for run in range(args.runs):
            out = tmp_path / f"out-{run}"
            seconds, cpu, text = convert_once(tmp_path / "kitti", out, args.workers)
            times.append(seconds)
            cpu_times.append(cpu)
            print(f"run {run + 1}: {seconds:.2f} s, {args.frames / seconds:.0f} frames/s, {cpu:.1f} CPU s")
            if run == 0:
                print(text.rstrip())
            shutil.rmtree(out)
    median = statistics.median(times)
    load = os.getloadavg()[0]
    print(f"convert kitti: {args.frames} frames, {cpus} CPUs, {args.workers} workers, hardlink: "
          f"median {median:.2f} s ({args.frames / median:.0f} frames/s), best {min(times):.2f} s "
          f"({args.frames / min(times):.0f} frames/s) over {args.runs} runs; "
          f"{statistics.median(cpu_times):.1f} CPU s a run; load average {load:.2f} at the end")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
