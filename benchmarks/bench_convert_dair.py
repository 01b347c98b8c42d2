"""Benchmark: convert 12,424 generated DAIR-V2X-C infrastructure frames with hard links.

12,424 is the number of infrastructure-side frames in DAIR-V2X-C. The frames come from
converters.dair_fixture (tiny 96x54 JPEGs, 4-14 labelled objects each, about 9 on average, like the
real 001366.json's 8), so the figure measures the converter (JSON parsing, geometry, record
writing, linking, indexing), not image decoding, which it never does. Target: under 20 s.

    .venv/bin/python benchmarks/bench_convert_dair.py [--frames N] [--workers N] [--workdir DIR] [--keep]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from converters import dair  # noqa: E402
from converters.dair_fixture import write_dair_tree  # noqa: E402

DAIR_V2X_C_INFRASTRUCTURE_FRAMES = 12_424
TARGET_S = 20.0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=DAIR_V2X_C_INFRASTRUCTURE_FRAMES)
    p.add_argument("--workdir", type=Path, default=None, help="where to build the tree (default: a temporary folder)")
    p.add_argument("--keep", action="store_true", help="keep the generated tree and the output")
    p.add_argument("--variant", choices=("i", "c"), default="c")
    p.add_argument("--workers", type=int, default=None, help="converter processes (default: the converter's default)")
    args = p.parse_args(argv)

    work = Path(tempfile.mkdtemp(prefix="bench-dair-", dir=args.workdir))
    try:
        start = time.perf_counter()
        fixture = write_dair_tree(work / "infrastructure-side", args.frames, seed=0, variant=args.variant)
        print(f"generated {args.frames} DAIR-V2X-{args.variant.upper()} frames in {time.perf_counter() - start:.1f} s")
        # Flush the freshly written tree first: on ext4 every record's fsync would otherwise wait for
        # the generator's dirty pages too, and the figure would measure the generator's writeback.
        os.sync()
        print(f"load average before converting: {os.getloadavg()[0]:.2f}")

        parser = argparse.ArgumentParser()
        dair.add_arguments(parser)
        argv_convert = [str(fixture.root), "--out", str(work / "out"), "--link", "hardlink"]
        if args.workers is not None:
            argv_convert += ["--workers", str(args.workers)]
        ns = parser.parse_args(argv_convert)
        start = time.perf_counter()
        code = dair.run(ns)
        seconds = time.perf_counter() - start
        rate = args.frames / seconds
        verdict = "meets" if seconds < TARGET_S * args.frames / DAIR_V2X_C_INFRASTRUCTURE_FRAMES else "MISSES"
        print(f"convert dair: {args.frames} frames in {seconds:.2f} s = {rate:.0f} frames/s "
              f"(hard links, {ns.workers} workers, {os.cpu_count()} CPUs; {verdict} the {TARGET_S:.0f} s target "
              f"for 12,424 frames)")
        return code
    finally:
        if args.keep:
            print(f"kept {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
