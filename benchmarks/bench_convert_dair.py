"""Benchmark: convert 12,424 generated DAIR-V2X-C infrastructure frames with hard links.

12,424 is the number of infrastructure-side frames in DAIR-V2X-C. The frames come from
omnigen.converters.dair_fixture (tiny 96x54 JPEGs, 4-14 labelled objects each, about 9 on average, like the
real 001366.json's 8), so the figure measures the converter (JSON parsing, geometry, record
writing, linking, indexing); each image is decoded in full (omnigen.images.check_image), which at
96x54 costs little: benchmarks/bench_image_check.py measures that check at real sizes. Target: under 20 s.

Prints every run, the median of --repeats runs, and then where a frame's CPU time goes, step by
step, measured serially on --steps frames. --tree DIR keeps the generated tree there and
reuses it on later calls (generating 12,424 frames takes longer than converting them).

    .venv/bin/python benchmarks/bench_convert_dair.py [--frames N] [--repeats N] [--workers N]
        [--steps N] [--tree DIR] [--workdir DIR] [--keep]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.converters import dair  # noqa: E402
from omnigen.converters.dair_fixture import write_dair_tree  # noqa: E402
from omnigen.writer import DatasetWriter  # noqa: E402

DAIR_V2X_C_INFRASTRUCTURE_FRAMES = 12_424
TARGET_S = 20.0


def convert_once(tree: Path, out: Path, workers: int | None, quiet: bool) -> tuple[float, int, int]:
    """(seconds, exit code, workers) of one `omnigen convert dair` run into a fresh `out`."""
    shutil.rmtree(out, ignore_errors=True)
    os.sync()  # the previous run's deletion and writes are flushed before the clock starts, not during
    parser = argparse.ArgumentParser()
    dair.add_arguments(parser)
    argv = [str(tree), "--out", str(out), "--link", "hardlink"]
    if workers is not None:
        argv += ["--workers", str(workers)]
    ns = parser.parse_args(argv)
    start = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()) if quiet else contextlib.nullcontext():
        code = dair.run(ns)
    return time.perf_counter() - start, code, ns.workers


def step_costs(tree: Path, out: Path, n: int) -> list[tuple[str, float]]:
    """CPU milliseconds per frame of each step, measured serially on the first n frames.

    The steps of omnigen.converters.common's frame loop, done here one by one so that each can be timed;
    make_objects (projection, silhouettes, self-occlusion, record assembly) is split out of the
    DAIR-specific work by timing it where convert calls it.
    """
    shutil.rmtree(out, ignore_errors=True)
    converter = dair.DairConverter(tree)
    keys = converter.keys()[:n]
    writer = DatasetWriter(out, durable=False)
    spent = {"objects": 0.0, "convert": 0.0, "place": 0.0, "write": 0.0, "finalize": 0.0}
    make_objects = dair.make_objects

    def timed_make_objects(*args, **kwargs):
        start = time.process_time()
        try:
            return make_objects(*args, **kwargs)
        finally:
            spent["objects"] += time.process_time() - start

    dair.make_objects = timed_make_objects
    try:
        for key in keys:
            t0 = time.process_time()
            frame = converter.convert(key)
            t1 = time.process_time()
            frame.image.place(out / frame.record.image, "hardlink")
            t2 = time.process_time()
            writer.write(frame.record)
            t3 = time.process_time()
            spent["convert"] += t1 - t0
            spent["place"] += t2 - t1
            spent["write"] += t3 - t2
    finally:
        dair.make_objects = make_objects
    t = time.process_time()
    writer.finalize(show_progress=False)
    spent["finalize"] = time.process_time() - t
    ms = {k: v / len(keys) * 1000 for k, v in spent.items()}
    return [
        ("DAIR-specific work: three JSON files, image check, label parsing, ground fit", ms["convert"] - ms["objects"]),
        ("make_objects: boxes, projection, silhouettes (shapely), self-occlusion, records", ms["objects"]),
        ("placing the image (hard link)", ms["place"]),
        ("writing the record: to_dict, validation (FrameRecord.from_dict), JSON, atomic write", ms["write"]),
        ("finalize (index, manifest)", ms["finalize"]),
    ]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=DAIR_V2X_C_INFRASTRUCTURE_FRAMES)
    p.add_argument("--repeats", type=int, default=3, help="conversions to time; the median is the figure")
    p.add_argument("--workdir", type=Path, default=None, help="where to build the tree (default: a temporary folder)")
    p.add_argument("--tree", type=Path, default=None,
                   help="keep the generated tree in this folder and reuse it when it is already there")
    p.add_argument("--keep", action="store_true", help="keep the generated tree and the output")
    p.add_argument("--variant", choices=("i", "c"), default="c")
    p.add_argument("--workers", type=int, default=None, help="converter processes (default: the converter's default)")
    p.add_argument("--steps", type=int, default=1000, help="frames for the per-step CPU table (0: skip it)")
    args = p.parse_args(argv)

    work = Path(tempfile.mkdtemp(prefix="bench-dair-", dir=args.workdir))
    try:
        tree = (args.tree / f"{args.variant}-{args.frames}") if args.tree else work / "tree"
        side = tree / "infrastructure-side"
        if not (side / "data_info.json").is_file():
            start = time.perf_counter()
            shutil.rmtree(tree, ignore_errors=True)
            write_dair_tree(side, args.frames, seed=0, variant=args.variant)
            print(f"generated {args.frames} DAIR-V2X-{args.variant.upper()} frames in {time.perf_counter() - start:.1f} s")
        else:
            print(f"reusing {args.frames} generated DAIR-V2X-{args.variant.upper()} frames in {tree}")
        # Flush the tree first: on ext4 every record's fsync would otherwise wait for the
        # generator's dirty pages too, and the figure would measure the generator's writeback.
        os.sync()
        times = []
        code = 0
        for i in range(max(1, args.repeats)):
            print(f"load average before run {i + 1}: {os.getloadavg()[0]:.2f}")
            seconds, code, workers = convert_once(tree, work / "out", args.workers, quiet=i > 0)
            times.append(seconds)
            print(f"run {i + 1}: {seconds:.2f} s")
        seconds = statistics.median(times)
        rate = args.frames / seconds
        verdict = "meets" if seconds < TARGET_S * args.frames / DAIR_V2X_C_INFRASTRUCTURE_FRAMES else "MISSES"
        print(f"convert dair: {args.frames} frames in {seconds:.2f} s (median of {len(times)}; min {min(times):.2f}, "
              f"max {max(times):.2f}) = {rate:.0f} frames/s (hard links, {workers} workers, {os.cpu_count()} CPUs; "
              f"{verdict} the {TARGET_S:.0f} s target for 12,424 frames)")
        if args.steps > 0:
            rows = step_costs(side, work / "steps", min(args.steps, args.frames))
            print(f"CPU per frame by step, serially on {min(args.steps, args.frames)} frames "
                  f"(load average {os.getloadavg()[0]:.2f}):")
            for name, ms in rows:
                print(f"  {ms:6.3f} ms  {name}")
            print(f"  {sum(ms for _, ms in rows):6.3f} ms  total")
        return code
    finally:
        if args.keep:
            print(f"kept {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
