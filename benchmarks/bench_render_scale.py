"""Rendering at scale: Ray's overhead against the local executor, and frames per CPU-hour.

1. Overhead (issue 7's target: ratio <= 1.15). The same raster frames (default: 20, drone rig,
   city `downtown` seed 0, 256 x 256) rendered end to end (building the city and the backend,
   every frame, the index and the manifest) by the local executor (`Renderer(job).run()`, one
   process: no scenes drawn ahead in a second one) and by the Ray executor with one worker (one actor: the same single render process,
   plus Ray's scheduling, the actor's start and the driver's bookkeeping), on a local Ray started
   before the clock (a running cluster, as with `--ray-address`); `ray.init` is timed apart.
   Each is run `--repeats` times into a fresh folder; the medians are compared:
   ratio = median Ray seconds / median local seconds. The ratio with two workers is printed too
   (on this 2-core machine that is a speed-up, not an overhead).
2. Cost (`--cost`): frames per CPU-hour for raster and each Cycles quality preset at a small size
   (`--cost-size`, default 160 x 160, drone rig, downtown): `--cost-frames` frames after a first
   frame that builds the city and the backend (not counted); CPU time is this process's, all
   threads (`time.process_time`), so frames per CPU-hour = 3600 / CPU seconds per frame.

    .venv/bin/python benchmarks/bench_render_scale.py [--frames 20] [--size 256] [--repeats 3] [--no-ray]
        [--cost] [--cost-size 160] [--cost-frames 2] [--cost-only]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _job(out: Path, frames: int, size: int, scene: str, seed: int, backend: str = "raster", quality: str = "fast"):
    from omnigen.rigs.render import RenderJob

    # ahead=False: every scene drawn in the render process, as a Ray actor draws them
    return RenderJob(rig="drone", frames=frames, out=out, seed=seed, scene=scene, width=size, height=size,
                     backend=backend, quality=quality, ahead=False)


def time_local(frames: int, size: int, scene: str, seed: int) -> float:
    from omnigen.rigs.render import Renderer

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        s = Renderer(_job(Path(tmp) / "local", frames, size, scene, seed)).run(show_progress=False)
        dt = time.perf_counter() - t0
    assert s.rendered == frames and s.finalized
    return dt


def time_ray(frames: int, size: int, scene: str, seed: int, workers: int) -> float:
    from omnigen.rigs.ray_executor import run_ray

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        s = run_ray(_job(Path(tmp) / "ray", frames, size, scene, seed), workers=workers, show_progress=False)
        dt = time.perf_counter() - t0
    assert s.rendered == frames and s.finalized and not s.failed
    return dt


def overhead(args) -> None:
    import ray

    print(f"overhead: {args.frames} raster frames, drone rig, {args.scene} seed {args.seed}, {args.size}x{args.size}, "
          f"{args.repeats} runs each, median")
    t0 = time.perf_counter()
    ray.init(num_cpus=os.cpu_count(), include_dashboard=False, log_to_driver=False, configure_logging=False)
    init_s = time.perf_counter() - t0
    try:
        local, ray1, ray2 = [], [], []
        for r in range(args.repeats):  # interleaved, so load on the shared machine hits both alike
            local.append(time_local(args.frames, args.size, args.scene, args.seed))
            ray1.append(time_ray(args.frames, args.size, args.scene, args.seed, workers=1))
            if args.two_workers:
                ray2.append(time_ray(args.frames, args.size, args.scene, args.seed, workers=2))
            print(f"  run {r + 1}: local {local[-1]:.2f} s, ray 1 worker {ray1[-1]:.2f} s"
                  + (f", ray 2 workers {ray2[-1]:.2f} s" if ray2 else ""), flush=True)
    finally:
        ray.shutdown()
    ml, m1 = statistics.median(local), statistics.median(ray1)
    print(f"ray.init (local cluster, {os.cpu_count()} CPUs): {init_s:.2f} s (not in the ratio)")
    print(f"local executor: {ml:.2f} s ({args.frames / ml:.3f} frames/s)")
    print(f"ray executor, 1 worker: {m1:.2f} s ({args.frames / m1:.3f} frames/s)")
    print(f"RATIO ray/local (1 worker, same render processes): {m1 / ml:.3f}  (target <= 1.15)")
    print(f"ratio counting ray.init: {(m1 + init_s) / ml:.3f}")
    if ray2:
        m2 = statistics.median(ray2)
        print(f"ray executor, 2 workers: {m2:.2f} s ({args.frames / m2:.3f} frames/s), speed-up over local {ml / m2:.2f}x")


def cost(args) -> None:
    from omnigen.rigs.render import Renderer

    n = args.cost_frames
    print(f"cost: drone rig, {args.scene} seed {args.seed}, {args.cost_size}x{args.cost_size}, {n} timed frames after a "
          f"build frame; CPU = this process, all threads")
    rows = []
    for backend, quality in [("raster", "fast"), ("cycles", "preview"), ("cycles", "fast"), ("cycles", "final")]:
        if backend == "cycles" and args.no_cycles:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            r = Renderer(_job(Path(tmp) / quality, n + 1, args.cost_size, args.scene, args.seed, backend, quality))
            r.render_frame(0)
            c0, w0 = time.process_time(), time.perf_counter()
            for i in range(1, n + 1):
                r.render_frame(i)
            cpu, wall = (time.process_time() - c0) / n, (time.perf_counter() - w0) / n
            r.close()
        name = backend if backend == "raster" else f"cycles {quality}"
        rows.append((name, wall, cpu, 3600 / cpu))
        print(f"  {name:15s} wall {wall:7.2f} s/frame  CPU {cpu:7.2f} s/frame  {3600 / cpu:8.0f} frames per CPU-hour",
              flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--scene", default="downtown")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--two-workers", action="store_true", help="also time Ray with 2 workers")
    ap.add_argument("--cost", action="store_true", help="also print frames per CPU-hour per quality preset")
    ap.add_argument("--cost-only", action="store_true")
    ap.add_argument("--cost-size", type=int, default=160)
    ap.add_argument("--cost-frames", type=int, default=2)
    ap.add_argument("--no-cycles", action="store_true")
    args = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, python {platform.python_version()}")
    if not args.cost_only:
        overhead(args)
    if args.cost or args.cost_only:
        cost(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
