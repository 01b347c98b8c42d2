"""The `omnigen` command: one entry point, short verbs, a summary table at the end.

Exit codes: 0 success; 1 the command ran and found problems (bad frames skipped, invalid dataset);
2 usage errors.

The CLI sits on top of everything: it imports the parts (converters, scenes, detector) lazily,
inside the command that needs them, so `omnigen --help` stays fast and the parts never import it.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path

from omnigen import __version__
from omnigen.files import LINK_MODES

COMMANDS: dict[str, str] = {
    # verb: module exposing add_arguments(parser) and run(args) -> int; modules import their heavy
    # dependencies (torch, pycocotools) inside run, so building the parser stays fast.
    "train": "omnigen.detector.train_command",
    "predict": "omnigen.detector.predict_command",
    "eval": "omnigen.detector.eval_command",
    "bev": "omnigen.detector.bev_command",
    "eval-kitti": "omnigen.detector.kitti_eval_command",
    "calib-sensitivity": "omnigen.detector.calib_command",
}


EXPORTERS: dict[str, str] = {
    # format: module exposing add_arguments(parser) and run(args) -> int
    "kitti": "omnigen.converters.kitti_export",
    "onnx": "omnigen.detector.export_onnx",
}


# ---------------------------------------------------------------------------------------------
# validate
# ---------------------------------------------------------------------------------------------


def _add_validate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("validate", help="check a dataset: schema, finite values, files present, unique ids")
    p.add_argument("dataset", type=Path)
    p.add_argument("--max-problems", type=int, default=50, help="how many problems to list (all are counted)")
    p.set_defaults(func=_run_validate)


def _run_validate(args: argparse.Namespace) -> int:
    from omnigen.checks import check_dataset
    from omnigen.progress import print_table

    start = time.perf_counter()
    n, problems = check_dataset(args.dataset)
    for p in problems[: args.max_problems]:
        print(f"  {p}")
    if len(problems) > args.max_problems:
        print(f"  ... and {len(problems) - args.max_problems} more")
    print_table(f"validate {args.dataset}", ["frames", "problems", "seconds"],
                [[n, len(problems), round(time.perf_counter() - start, 2)]])
    if problems:
        print(f"{args.dataset}: INVALID ({len(problems)} problems)")
        return 1
    print(f"{args.dataset}: valid")
    return 0


# ---------------------------------------------------------------------------------------------
# export
# ---------------------------------------------------------------------------------------------


def _add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write a dataset in another format (coco, yolo, kitti), or a model as ONNX")
    formats = p.add_subparsers(dest="format", required=True, metavar="FORMAT")
    coco = formats.add_parser("coco", help="COCO keypoints JSON (pycocotools reads it)")
    coco.add_argument("dataset", type=Path)
    coco.add_argument("--out", type=Path, required=True, help="output .json file")
    coco.add_argument("--split", default=None, help="only frames of this split (splits/<name>.txt)")
    coco.add_argument("--taxonomy", default=None, help="fine, coarse or a TOML file (default: the dataset's)")
    coco.set_defaults(func=_run_export_coco)
    yolo = formats.add_parser("yolo", help="Ultralytics pose layout (images/, labels/, data.yaml)")
    yolo.add_argument("dataset", type=Path)
    yolo.add_argument("--out", type=Path, required=True, help="output folder")
    yolo.add_argument("--taxonomy", default=None, help="fine, coarse or a TOML file (default: the dataset's)")
    yolo.add_argument("--link", choices=LINK_MODES, default="hardlink", help="how images are placed")
    yolo.set_defaults(func=_run_export_yolo)
    _add_plugins(formats, EXPORTERS)


def _run_export_coco(args: argparse.Namespace) -> int:
    from omnigen.coco import export_coco
    from omnigen.dataset import Dataset
    from omnigen.progress import print_table

    start = time.perf_counter()
    ds = Dataset.open(args.dataset)
    counts = export_coco(ds, args.out, args.split, _taxonomy_for(ds, args.taxonomy))
    print_table(f"export coco -> {args.out}", ["images", "annotations", "categories", "seconds"],
                [[counts["images"], counts["annotations"], counts["categories"], round(time.perf_counter() - start, 2)]])
    return 0


def _taxonomy_for(ds, name: str | None):
    """The taxonomy asked for, else the one the dataset's manifest records, else fine."""
    from omnigen.taxonomy import load_taxonomy, recorded_taxonomy

    return load_taxonomy(name) if name else recorded_taxonomy(ds.manifest)


def _run_export_yolo(args: argparse.Namespace) -> int:
    from omnigen.dataset import Dataset
    from omnigen.progress import print_table
    from omnigen.yolo import export_yolo

    start = time.perf_counter()
    ds = Dataset.open(args.dataset)
    counts = export_yolo(ds, args.out, _taxonomy_for(ds, args.taxonomy), args.link)
    print_table(f"export yolo -> {args.out}", ["images", "objects", "classes", "seconds"],
                [[counts["images"], counts["objects"], counts["classes"], round(time.perf_counter() - start, 2)]])
    print(f"Ultralytics dataset YAML: {args.out / 'data.yaml'}")
    return 0


# ---------------------------------------------------------------------------------------------
# merge
# ---------------------------------------------------------------------------------------------


def _add_merge(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("merge", help="merge source datasets into UrbanOmniView with a held-out test split")
    p.add_argument("sources", type=Path, nargs="*", help="source datasets (render and convert outputs)")
    p.add_argument("--out", type=Path, required=True, help="output dataset folder")
    p.add_argument("--taxonomy", default=None,
                   help="fine, coarse or a TOML file; recorded in the manifest (default: fine; with --update, the earlier merge's)")
    p.add_argument("--test-fraction", type=float, default=None,
                   help="share of each source and view held out (default: 0.10; with --update, the earlier merge's)")
    p.add_argument("--seed", type=int, default=None,
                   help="seed of the test-split draw (default: 0; with --update, the earlier merge's)")
    p.add_argument("--split-file", type=Path, action="append", default=[],
                   help="a list of frame ids (or source ids such as KITTI's 000123); the file's stem names "
                        "the split; repeatable (e.g. train.txt and val.txt)")
    p.add_argument("--update", action="store_true", help="add sources to an existing merge, keeping its splits")
    p.add_argument("--link", choices=LINK_MODES, default="hardlink", help="how images are placed")
    p.set_defaults(func=_run_merge)


def _run_merge(args: argparse.Namespace) -> int:
    from omnigen.merge import merge
    from omnigen.progress import print_table
    from omnigen.taxonomy import load_taxonomy

    if not args.sources and not args.update:
        print("omnigen merge: give at least one source dataset", file=sys.stderr)
        return 2
    r = merge(args.sources, args.out, load_taxonomy(args.taxonomy) if args.taxonomy else None, args.test_fraction,
              args.seed, args.split_file, args.update, args.link)
    print_table(f"merge -> {args.out}", ["source", "frames"], sorted(r.by_source.items()))
    print_table("splits", ["split", "frames"], sorted(r.by_split.items()))
    test = r.by_split.get("test", 0)  # whole groups make the share reached differ from the one asked
    print(f"test split: {test} of {r.frames} frames ({test / max(r.frames, 1):.3f}; asked {r.test_fraction:g})")
    for path, n in sorted(r.unmatched_lines.items()):
        print(f"  {path}: {n} lines name no frame of these sources (left out)")
    links = ", ".join(f"{k} {v}" for k, v in sorted(r.link_modes.items())) or "-"
    print_table("summary", ["frames", "objects", "unique images", "images placed", "seconds"],
                [[r.frames, r.objects, r.unique_images, links, round(r.seconds, 2)]])
    return 0


# ---------------------------------------------------------------------------------------------
# stats
# ---------------------------------------------------------------------------------------------


def _add_stats(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stats", help="write a dataset's statistics report (index.html, stats.json, PNG figures)")
    p.add_argument("dataset", type=Path)
    p.add_argument("--out", type=Path, required=True, help="report folder (created; files in it are replaced)")
    p.add_argument("--gallery", type=int, default=6, help="sample frames drawn with cuboids and BEV (0: none)")
    p.add_argument("--no-check-images", dest="check_images", action="store_false",
                   help="do not open every image's header (the one step that reads a file per frame)")
    p.add_argument("--prior-sigma", type=float, default=None,
                   help="flag dimensions this many spreads from their class prior (default: omnigen.priors.FAR_SIGMA)")
    p.add_argument("--seed", type=int, default=0, help="seed of the gallery's pick")
    p.add_argument("--jobs", type=int, default=0, help="processes drawing figures (0: up to 4, one per core)")
    p.set_defaults(func=_run_stats)


def _run_stats(args: argparse.Namespace) -> int:
    import os

    from omnigen.dataset import Dataset
    from omnigen.priors import FAR_SIGMA
    from omnigen.progress import print_table
    from omnigen.stats.report import write_report

    start = time.perf_counter()
    ds = Dataset.open(args.dataset)
    opened = time.perf_counter() - start
    jobs = args.jobs if args.jobs > 0 else max(1, min(4, os.cpu_count() or 1))
    sigma = FAR_SIGMA if args.prior_sigma is None else args.prior_sigma
    r = write_report(ds, args.out, args.gallery, args.check_images, sigma, args.seed, jobs)
    health = r.stats["health"]
    overall = r.stats["overall"]
    print_table("classes", ["class", "objects", "share", "frames holding it"],
                [[c, n, f"{100 * overall['class_fractions'][c]:.1f}%", overall["class_frames"][c]]
                 for c, n in overall["classes"].items() if n])
    print_table("health", ["check", "count"], [[c["title"], c["count"]] for c in health["checks"]])
    steps = {"open dataset": opened, **r.timings, "total": time.perf_counter() - start}
    print_table("seconds", ["step", "seconds"], [[k, round(v, 2)] for k, v in steps.items()])
    print_table(f"stats {args.dataset} -> {args.out}", ["frames", "objects", "figures", "findings"],
                [[len(ds), len(ds.objects), r.figures, health["problems"]]])
    print(f"report: {args.out / 'index.html'}")
    return 0


# ---------------------------------------------------------------------------------------------
# show
# ---------------------------------------------------------------------------------------------


def _add_show(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("show", help="draw one frame's cuboids, boxes and ignore regions (and its BEV) as a PNG")
    p.add_argument("dataset", type=Path)
    p.add_argument("frame_id", help="a frame id (or the part after the source prefix when it is unique)")
    p.add_argument("--out", type=Path, default=None, help="output PNG (default: FRAME_ID.png here)")
    p.add_argument("--bev", action="store_true", help="add the bird's-eye view of the ground plane beside the image")
    p.add_argument("--scale", type=float, default=None,
                   help="display scale (default: whole-number upscale of small images)")
    p.add_argument("--margin", type=float, default=0.0,
                   help="border around the image, as a fraction of its size, to show corners outside it (e.g. 0.2)")
    p.set_defaults(func=_run_show)


def _run_show(args: argparse.Namespace) -> int:
    from omnigen.dataset import Dataset
    from omnigen.draw import render_frame

    ds = Dataset.open(args.dataset)
    frame_id = _resolve_frame_id(ds.frame_ids, args.frame_id)
    if frame_id is None:
        import difflib

        close = difflib.get_close_matches(args.frame_id, ds.frame_ids, n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        print(f"omnigen show: error: {args.dataset}: no frame {args.frame_id!r}{hint}", file=sys.stderr)
        return 1
    rec = ds.frame(frame_id)
    view = render_frame(rec, ds.path(rec.image), bev=args.bev, scale=args.scale, margin=args.margin)
    out = args.out or Path(f"{frame_id}.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    view.image.save(out)
    note = f" (image: {view.image_error})" if view.image_error else ""
    print(f"{frame_id}: {len(rec.objects)} objects, {len(rec.ignore_regions)} ignore regions -> {out}{note}")
    return 0


def _resolve_frame_id(frame_ids: list[str], wanted: str) -> str | None:
    """The frame id itself, else the one frame whose id ends with '-' + wanted (kitti-000123 for 000123)."""
    if wanted in frame_ids:
        return wanted
    matches = [f for f in frame_ids if f.endswith("-" + wanted)]
    return matches[0] if len(matches) == 1 else None


# ---------------------------------------------------------------------------------------------
# render
# ---------------------------------------------------------------------------------------------


def _add_render(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="render annotated frames of the procedural city from a camera rig")
    p.add_argument("--rig", required=True, help="ego, pole, drone or a rig TOML file")
    p.add_argument("--frames", type=int, required=True, help="how many frames (indices start..start+N-1)")
    p.add_argument("--out", type=Path, required=True, help="output dataset folder (rerun to resume)")
    p.add_argument("--seed", type=int, default=0, help="dataset seed: the city and every frame follow from it")
    p.add_argument("--scene", default="downtown",
                   help="city preset (downtown, arterial, suburban, intersection, tiny) or a TOML file; or a mix "
                        "NAME,NAME,... of which each --seed draws one (seed mod the count)")
    p.add_argument("--width", type=int, default=None, help="image width (default: the rig's)")
    p.add_argument("--height", type=int, default=None, help="image height (default: the rig's)")
    p.add_argument("--backend", choices=("cycles", "raster"), default="cycles", help="Cycles, or the fast raster preview")
    p.add_argument("--quality", choices=("preview", "fast", "final"), default="fast",
                   help="Cycles samples, denoising and bounces (raster ignores it)")
    p.add_argument("--start", type=int, default=0, help="index of the first frame")
    p.add_argument("--weather", default=None, help="fix the weather (clear, overcast, rain, snow, fog); default: drawn per frame")
    p.add_argument("--time-of-day", default=None,
                   help="fix the time of day (dawn, morning, noon, afternoon, dusk, night); default: drawn per frame")
    p.add_argument("--fog-density", type=float, default=None, help="fix the fog density (1/m); default: drawn")
    p.add_argument("--precipitation", type=float, default=None, help="fix rain or snow intensity (0-1); default: drawn")
    p.add_argument("--save-blend", type=Path, default=None,
                   help="Cycles: also write the first rendered frame's scene as a .blend to open in Blender")
    p.add_argument("--labels", choices=("auto", "gl", "cycles"), default="auto",
                   help="Cycles: where depth, instance ids and silhouettes come from: gl (the raster id pass over "
                        "the same geometry, milliseconds), cycles (one-sample Cycles passes), auto (gl when a "
                        "headless OpenGL context can be made)")
    from omnigen.scenes.cycles_devices import DEVICE_KINDS  # plain Python, no bpy

    p.add_argument("--device", choices=DEVICE_KINDS, default="auto",
                   help="Cycles' compute devices: auto (the best GPU there is, OptiX > CUDA > HIP > oneAPI > Metal, "
                        "else the CPU), cpu, or one GPU type (an error if absent); not a frame-deciding argument: a "
                        "render resumes on any device (docs/rendering.md)")
    p.add_argument("--shard", default=None, metavar="K/N",
                   help="render only frames with index %% N == K-1 (1 <= K <= N) into the shared --out; the shard "
                        "that finds every frame of the run written finalizes (docs/rendering-at-scale.md)")
    p.add_argument("--fresh", action="store_true",
                   help="delete the folder's frames, index, manifest and recorded arguments first and start over "
                        "(a rerun with other arguments is refused without it)")
    p.add_argument("--finalize-only", action="store_true",
                   help="render nothing: build the index and manifest once every frame of the run is written")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local: this process renders; ray: frames fan out over a Ray cluster (optional extra)")
    p.add_argument("--ray-address", default=None,
                   help="Ray cluster to join (auto, host:6379, ray://host:10001); default: a local Ray for the run")
    p.add_argument("--ray-workers", type=int, default=None, help="concurrent render actors (default: CPUs / cpus-per-worker)")
    p.add_argument("--cpus-per-worker", type=float, default=1.0, help="CPUs Ray reserves for each render actor")
    p.add_argument("--frames-per-worker", type=int, default=100,
                   help="restart a Ray render actor after this many frames (keeps memory flat)")
    p.add_argument("--retries", type=int, default=2, help="retries of a failed frame on Ray before it is reported")
    p.set_defaults(func=_run_render)


def _run_render(args: argparse.Namespace) -> int:
    from omnigen.progress import print_table
    from omnigen.rigs.render import (RenderJob, Renderer, claim_render_folder, finalize_run, missing_frames, parse_shard,
                             render_args, start_over)

    if args.frames < 0 or args.seed < 0 or args.start < 0:
        print("omnigen render: --frames, --seed and --start must be >= 0", file=sys.stderr)
        return 2
    if args.frames_per_worker < 1 or args.retries < 0 or (args.ray_workers is not None and args.ray_workers < 1):
        print("omnigen render: --frames-per-worker and --ray-workers must be >= 1, --retries >= 0", file=sys.stderr)
        return 2
    try:
        shard = parse_shard(args.shard) if args.shard else (1, 1)
    except ValueError as exc:
        print(f"omnigen render: {exc}", file=sys.stderr)
        return 2
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
                    device=args.device)
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


# ---------------------------------------------------------------------------------------------
# convert
# ---------------------------------------------------------------------------------------------


def _add_convert(sub: argparse._SubParsersAction) -> None:
    from omnigen.converters import CONVERTERS

    p = sub.add_parser("convert", help="convert a public dataset (kitti, dair) into UrbanOmniView")
    names = p.add_subparsers(dest="converter", required=True, metavar="DATASET")
    _add_plugins(names, CONVERTERS)


def _add_plugins(subparsers: argparse._SubParsersAction, registry: dict[str, str]) -> None:
    """One subcommand per registry entry; the module gives add_arguments(parser) and run(args)."""
    for name, module_name in registry.items():
        # No fallback for a module that does not import: a missing or broken command is an error
        # here, not a stub that says "not built yet" (which let a deleted module pass every test).
        module = importlib.import_module(module_name)
        first = (module.__doc__ or "").strip().splitlines()[0]
        if first[1:2].islower():  # "Train the ..." -> "train the ...", as the built-in verbs read; not "KITTI"
            first = first[:1].lower() + first[1:]
        q = subparsers.add_parser(name, help=first.rstrip("."))
        module.add_arguments(q)
        q.set_defaults(func=module.run)


# ---------------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="omnigen",
        description="Training data for calibration-free monocular 3D object detection in cities.",
    )
    parser.add_argument("--version", action="version", version=f"omnigen {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_render(sub)
    _add_convert(sub)
    _add_merge(sub)
    _add_export(sub)
    _add_stats(sub)
    _add_show(sub)
    _add_validate(sub)
    _add_plugins(sub, COMMANDS)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted; finished frames are kept and a rerun resumes", file=sys.stderr)
        return 130
    except (ValueError, OSError, RuntimeError) as exc:  # readable one-line errors, no traceback
        print(f"omnigen {args.command}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
