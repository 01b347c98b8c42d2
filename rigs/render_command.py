"""Render annotated frames of the procedural city from a camera rig."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from omnigen.options import SEED_MAX, integer, number, seed
from omnigen.rigs.rig import RESOLUTION_RANGE

MAX_FRAMES = 10_000_000
"""Frames one run renders at most: each shard lists the run's indices before it starts, and ten
million of them already hold a few hundred MB; a larger dataset is several runs (--start)."""
MAX_RAY_WORKERS = 10_000
"""Concurrent render actors at most: each is a process holding a city; more is a typo."""
MAX_RETRIES = 100
"""A frame that fails this often fails for a reason a further try will not remove."""
MAX_SEQUENCE_LENGTH = 100_000
"""Instants of one sequence at most: its world rolls out from t = 0 for every resumed sequence."""
DEFAULT_FPS = 10.0
FPS_RANGE = (0.01, 1000.0)
"""Instants per second: from one every 100 s to 1 ms steps (the motion steps at 50 ms and interpolates)."""
CPUS_PER_WORKER = (0.0001, 1024.0)
"""Ray's smallest fraction of a CPU, and more CPUs than one node has: an actor asking for more
would wait for ever for a node to place it on."""


def _shard(text: str) -> tuple[int, int]:
    """--shard K/N at parse time (omnigen.rigs.render.parse_shard, imported only when given)."""
    from omnigen.rigs.render import parse_shard

    try:
        return parse_shard(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix(f"--shard {text!r}: ")) from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    from omnigen.scenes.weather import FOG_DENSITY_RANGE, PRECIPITATION_RANGE

    pixels = integer(*RESOLUTION_RANGE)
    p.add_argument("--rig", required=True,
                   help="ego, pole, drone or a rig TOML file; or several, NAME,NAME,... (e.g. ego,pole,drone): "
                        "each instant of one world seen by every rig, placed around one junction")
    p.add_argument("--frames", type=integer(1, MAX_FRAMES), required=True,
                   help="how many frames (indices start..start+N-1)")
    p.add_argument("--out", type=Path, required=True, help="output dataset folder (rerun to resume)")
    p.add_argument("--seed", type=seed(), default=0,
                   help="dataset seed: the city and every frame follow from it (default %(default)s)")
    p.add_argument("--scene", default="downtown",
                   help="city preset (downtown, arterial, suburban, intersection, tiny) or a TOML file; or a mix "
                        "NAME,NAME,... of which each --seed draws one (seed mod the count)")
    p.add_argument("--width", type=pixels, default=None, help="image width (default: the rig's)")
    p.add_argument("--height", type=pixels, default=None, help="image height (default: the rig's)")
    p.add_argument("--backend", choices=("cycles", "raster"), default="cycles", help="Cycles, or the fast raster preview")
    p.add_argument("--quality", choices=("preview", "fast", "final"), default="fast",
                   help="Cycles samples, denoising and bounces (raster ignores it)")
    p.add_argument("--start", type=integer(0, SEED_MAX), default=0,
                   help="index of the first frame (default %(default)s)")
    p.add_argument("--sequence-length", type=integer(1, MAX_SEQUENCE_LENGTH), default=1,
                   help="instants per sequence: L consecutive instants of one moving world, seen by a camera "
                        "held still (--frames and --start multiples of it); 1, the default: independent frames")
    p.add_argument("--fps", type=number(*FPS_RANGE), default=DEFAULT_FPS,
                   help="instants per second within a sequence (default %(default)g)")
    p.add_argument("--weather", default=None, help="fix the weather (clear, overcast, rain, snow, fog); default: drawn per frame")
    p.add_argument("--time-of-day", default=None,
                   help="fix the time of day (dawn, morning, noon, afternoon, dusk, night); default: drawn per frame")
    p.add_argument("--fog-density", type=number(*FOG_DENSITY_RANGE), default=None,
                   help="fix the fog density (1/m); default: drawn")
    p.add_argument("--precipitation", type=number(*PRECIPITATION_RANGE), default=None,
                   help="fix rain or snow intensity (0: none, 1: the heaviest); default: drawn")
    p.add_argument("--save-blend", type=Path, default=None,
                   help="Cycles: also write the first rendered frame's scene as a .blend to open in Blender")
    p.add_argument("--labels", choices=("auto", "gl", "cycles"), default="auto",
                   help="Cycles: where depth, instance ids and silhouettes come from: gl (the raster id pass over "
                        "the same geometry), cycles (one-sample Cycles passes), auto (gl when a headless OpenGL "
                        "context can be made)")
    from omnigen.scenes.cycles_devices import DEVICE_KINDS  # plain Python, no bpy

    p.add_argument("--device", choices=DEVICE_KINDS, default="auto",
                   help="Cycles' compute devices: auto (the best GPU there is, OptiX > CUDA > HIP > oneAPI > Metal, "
                        "else the CPU), cpu, or one GPU type (an error if absent); not a frame-deciding argument: a "
                        "render resumes on any device (docs/rendering.md)")
    p.add_argument("--shard", type=_shard, default=None, metavar="K/N",
                   help="render only frames with index %% N == K-1 (1 <= K <= N) into the shared --out; the shard "
                        "that finds every frame of the run written finalizes (docs/rendering-at-scale.md); default: every frame")
    p.add_argument("--fresh", action="store_true",
                   help="delete the folder's frames, index, manifest and recorded arguments first and start over "
                        "(a rerun with other arguments is refused without it)")
    p.add_argument("--finalize-only", action="store_true",
                   help="render nothing: build the index and manifest once every frame of the run is written")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local: this process renders; ray: frames fan out over a Ray cluster (optional extra)")
    p.add_argument("--ray-address", default=None,
                   help="Ray cluster to join (auto, host:6379, ray://host:10001); default: a local Ray for the run")
    p.add_argument("--ray-workers", type=integer(1, MAX_RAY_WORKERS), default=None,
                   help="concurrent render actors (default: CPUs / cpus-per-worker)")
    p.add_argument("--cpus-per-worker", type=number(*CPUS_PER_WORKER), default=1.0,
                   help="CPUs Ray reserves for each render actor (default %(default)g)")
    p.add_argument("--frames-per-worker", type=integer(1, MAX_FRAMES), default=100,
                   help="restart a Ray render actor after this many frames, which keeps memory flat "
                        "(default %(default)s)")
    p.add_argument("--retries", type=integer(0, MAX_RETRIES), default=2,
                   help="retries of a failed frame on Ray before it is reported (default %(default)s)")


def run(args: argparse.Namespace) -> int:
    from omnigen.progress import print_table
    from omnigen.rigs.render import (RenderJob, Renderer, claim_render_folder, finalize_run, missing_frames,
                                     render_args, start_over)

    shard = args.shard or (1, 1)  # checked when parsed, as every number of this command is
    from omnigen.scenes.generate import FrameOverrides
    from omnigen.scenes.weather import TIMES_OF_DAY, WEATHER_KINDS

    if args.weather not in (None, *WEATHER_KINDS) or args.time_of_day not in (None, *TIMES_OF_DAY):
        print(f"omnigen render: --weather is one of {', '.join(WEATHER_KINDS)}; "
              f"--time-of-day one of {', '.join(TIMES_OF_DAY)}", file=sys.stderr)
        return 2
    if args.save_blend is not None and args.backend != "cycles":
        print("omnigen render: --save-blend needs --backend cycles", file=sys.stderr)
        return 2
    if args.backend != "cycles" and args.device not in ("auto", "cpu"):
        print(f"omnigen render: --device {args.device} needs --backend cycles (the raster backend renders through "
              "OpenGL on the device its EGL driver offers)", file=sys.stderr)
        return 2
    if args.backend == "cycles" and args.executor == "local" and args.device != "cpu" and not args.finalize_only:
        # Checked before anything is written (on Ray each worker checks its own machine).
        from omnigen.scenes.blender_backend import cycles_devices
        from omnigen.scenes.cycles_devices import DeviceUnavailable

        try:
            print(cycles_devices(args.device).note, file=sys.stderr)
        except DeviceUnavailable as exc:
            print(f"omnigen render: {exc}", file=sys.stderr)
            return 2
    overrides = FrameOverrides(weather=args.weather, time_of_day=args.time_of_day, fog_density=args.fog_density,
                               precipitation=args.precipitation)
    job = RenderJob(rig=args.rig, frames=args.frames, out=args.out, seed=args.seed, scene=args.scene,
                    width=args.width, height=args.height, backend=args.backend, quality=args.quality, start=args.start,
                    shard=shard, overrides=overrides, save_blend=args.save_blend, labels=args.labels,
                    device=args.device, sequence_length=args.sequence_length, fps=args.fps)
    if args.executor == "ray" and (job.sequences or job.cooperative):  # before anything is written
        said = f"--rig {args.rig}" if job.cooperative else f"--sequence-length {job.sequence_length}"
        print(f"omnigen render: --executor ray renders independent frames only, of one rig; run {said} "
              "locally (with --shard K/N for several processes)", file=sys.stderr)
        return 2
    if args.fresh:
        if args.finalize_only or shard[1] > 1:
            print("omnigen render: --fresh deletes every shard's frames: run it once, without --shard or "
                  "--finalize-only", file=sys.stderr)
            return 2
        deleted = start_over(args.out)
        if deleted:
            print(f"--fresh: deleted {deleted} frames of {args.out}")
    # Refused here, before any executor starts, when the folder's frames were rendered otherwise.
    claim_render_folder(job, render_args(job))
    if args.finalize_only:
        missing = missing_frames(job)
        if missing or not finalize_run(job):
            print(f"omnigen render --finalize-only: {len(missing)} of {args.frames} frames not written yet "
                  f"(first: {missing[:5]}); run the missing shards (or rerun to resume) first", file=sys.stderr)
            return 1
        print(f"finalized {args.out}: {args.frames} frames")
        return 0
    if args.executor == "ray":
        from omnigen.rigs.ray_executor import run_ray

        try:
            s = run_ray(job, address=args.ray_address, workers=args.ray_workers, cpus_per_worker=args.cpus_per_worker,
                        frames_per_worker=args.frames_per_worker, retries=args.retries)
        except RuntimeError as exc:
            if "needs Ray" not in str(exc):
                raise
            print(f"omnigen render: {exc}", file=sys.stderr)
            return 2
    else:
        s = Renderer(job).run()
    fps = s.rendered / s.seconds if s.seconds > 0 else 0.0
    title = f"render {args.rig} -> {args.out}" + (f" (shard {shard[0]}/{shard[1]})" if args.shard else "")
    print_table(title, ["rendered", "skipped", "failed", "objects", "redraws", "seconds", "frames/s"],
                [[s.rendered, s.skipped, len(s.failed), s.objects, s.redraws, round(s.seconds, 2), round(fps, 2)]])
    print_table("time by stage (s)", list(s.timings), [[round(v, 2) for v in s.timings.values()]])
    if s.failed:
        print(f"omnigen render: {len(s.failed)} frames failed: {s.failed[:20]}; rerun the command to retry them",
              file=sys.stderr)
        return 1
    if not s.finalized:
        print(f"not finalized yet: {len(missing_frames(job))} frames of the run are missing (other shards); "
              "the shard that completes the run finalizes, or run with --finalize-only", file=sys.stderr)
    return 0
