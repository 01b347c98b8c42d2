"""`omnigen render` speed: raster frames/s and Cycles seconds per frame at 640x640, and the overhead share.

Renders the default city (downtown) from the drone rig into a temporary folder with the real
pipeline (scene re-randomisation, camera, render, annotation, atomic writes) and prints, per
backend: frames, seconds per frame (the one-off city/backend build excluded and shown apart),
frames per second, time by stage, and the overhead share: the fraction of the per-frame time not
spent in the renderer's own core (Cycles' beauty path tracing; for raster the whole pyrender call
counts as the core). Resident memory is printed after the first and the last frame. Frames are
written as `omnigen render` writes them: each frame's files on a thread while the next is drawn
(the "write" stage is the time the loop waited for them; the last frame's writing is in the total).

Issue 6's targets: raster >= 3 annotated frames/s; Cycles --quality fast <= 8 s a frame, overhead
<= 10% of the frame time over 20 frames.

    .venv/bin/python benchmarks/bench_render.py [--raster-frames 21] [--cycles-frames 21] [--size 640] [--no-cycles]
        [--no-raster] [--memory-frames 200 [--memory-backend cycles] [--memory-size 96] [--memory-quality preview]]
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


def bench(backend: str, frames: int, size: int, quality: str, scene: str, seed: int) -> dict:
    from omnigen.rigs.render import RenderJob, Renderer

    with tempfile.TemporaryDirectory() as tmp:
        job = RenderJob(rig="drone", frames=frames, out=Path(tmp) / backend, seed=seed, scene=scene,
                        width=size, height=size, backend=backend, quality=quality, durable=False)
        r = Renderer(job)
        r.write_behind = True  # as `omnigen render` (Renderer.run) writes: each frame's files on a thread
        t0 = time.perf_counter()
        r.render_frame(0)
        r.flush()
        first = time.perf_counter() - t0
        rss_first = rss_mb()
        build = r.summary.timings["build"]
        base = dict(r.summary.timings)
        t1 = time.perf_counter()
        for i in range(1, frames):
            r.render_frame(i)
        r.flush()  # the last frame's files are part of the time
        loop = time.perf_counter() - t1
        rss_last = rss_mb()
        tm = {k: r.summary.timings[k] - base[k] for k in base}
        r.close()
    n = frames - 1
    core = tm["renderer_core"]
    return {"backend": backend, "frames": n, "s_per_frame": loop / n, "fps": n / loop, "first_frame_s": first,
            "build_s": build, "core_s_per_frame": core / n, "overhead_share": 1 - core / loop,
            "stages": {k: v / n for k, v in tm.items() if k not in ("build",)}, "rss_first": rss_first,
            "rss_last": rss_last, "objects": r.summary.objects, "redraws": r.summary.redraws}


def report(res: dict) -> None:
    from omnigen.progress import print_table

    rows = [["frames timed (after frame 0)", res["frames"]],
            ["seconds per frame", round(res["s_per_frame"], 3)],
            ["frames per second", round(res["fps"], 2)],
            ["renderer core, s per frame", round(res["core_s_per_frame"], 3)],
            ["overhead share (not core)", f"{100 * res['overhead_share']:.1f}%"],
            ["frame 0 incl. build, s", round(res["first_frame_s"], 2)],
            ["city + backend build, s", round(res["build_s"], 2)],
            ["objects annotated (all frames)", res["objects"]],
            ["camera redraws after annotation", res["redraws"]],
            ["resident MB after frame 0", round(res["rss_first"])],
            ["resident MB after last frame", round(res["rss_last"])]]
    rows += [[f"  stage {k}, s per frame", round(v, 3)] for k, v in res["stages"].items()]
    print_table(f"{res['backend']}: drone rig", ["measure", "value"], rows)


def memory(backend: str, frames: int, size: int, scene: str, seed: int, quality: str = "preview") -> None:
    """Resident memory every 10 frames over a long run (leaks show as steady growth), and the change
    from frame 20 to the last (issue 6: within 10% from frame 20 to frame 200)."""
    from omnigen.progress import print_table
    from omnigen.rigs.render import RenderJob, Renderer

    rows, at = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        r = Renderer(RenderJob(rig="drone", frames=frames, out=Path(tmp), seed=seed, scene=scene, width=size,
                               height=size, backend=backend, quality=quality, durable=False))
        for i in range(frames):
            r.render_frame(i)
            if (i + 1) % 10 == 0:
                at[i + 1] = rss_mb()
                blocks = r.backend.bs.datablock_counts() if backend == "cycles" else {}
                rows.append([i + 1, round(at[i + 1])] + ([" ".join(f"{k} {v}" for k, v in blocks.items())] if blocks else []))
        r.backend.close()
    head = ["frames", "resident MB"] + (["bpy datablocks"] if backend == "cycles" else [])
    print_table(f"{backend}: resident MB by frame ({size}x{size}, {quality})", head, rows)
    if 20 in at and frames in at and frames > 20:
        print(f"{backend}: resident MB after frame 20 {at[20]:.0f}, after frame {frames} {at[frames]:.0f}: "
              f"{100 * (at[frames] / at[20] - 1):+.1f}% (target within 10%)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--raster-frames", type=int, default=21)
    ap.add_argument("--cycles-frames", type=int, default=21)
    ap.add_argument("--size", type=int, default=640)
    ap.add_argument("--quality", default="fast")
    ap.add_argument("--scene", default="downtown")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-cycles", action="store_true")
    ap.add_argument("--no-raster", action="store_true")
    ap.add_argument("--memory-frames", type=int, default=0, help="also: a long run, RSS every 10 frames")
    ap.add_argument("--memory-backend", default="raster", choices=("raster", "cycles"))
    ap.add_argument("--memory-size", type=int, default=160, help="frame size of the memory run (square)")
    ap.add_argument("--memory-quality", default="preview")
    args = ap.parse_args()
    import os

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
          f"{args.size}x{args.size}, scene {args.scene} seed {args.seed}")
    if not args.no_raster:
        report(bench("raster", args.raster_frames, args.size, args.quality, args.scene, args.seed))
    if not args.no_cycles:
        report(bench("cycles", args.cycles_frames, args.size, args.quality, args.scene, args.seed))
    if args.memory_frames:
        memory(args.memory_backend, args.memory_frames, args.memory_size, args.scene, args.seed, args.memory_quality)
    return 0


if __name__ == "__main__":
    sys.exit(main())
