"""Default city build time and peak memory: description plus Blender scene (targets: < 10 s, < 2 GB).

Also prints, for issue 6's budget, what a frame re-randomisation costs (new agents, weather and
lighting drawn, and the Blender scene updated in place) and the raster preview's build and
render times. Every figure is measured in this process, from a cold start (imports included in
the first build, as a user's first command would pay them).

    .venv/bin/python benchmarks/bench_scene.py [--preset downtown] [--seed 0] [--frames 5] [--no-raster]

`--placement` instead counts issue 45's placement checks over `--cameras` cameras a rig (ego,
pole, drone), drawn as `omnigen render` draws them (frame i of seed s: the scene's frame i and
the camera stream rig_rng(s, i)), spread over the presets of PLACEMENT_PRESETS (the k-th with
seed k + 1): how many ego cameras stand over a driving lane looking along it, how many pole and
drone cameras see geometry within their rig's near_distance in at most max_near_share of the
image (the worst share printed), and the draws they took.

    .venv/bin/python benchmarks/bench_scene.py --placement [--cameras 100]
"""

from __future__ import annotations

import argparse
import math
import platform
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.options import integer  # noqa: E402


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


PLACEMENT_PRESETS = ("tiny", "downtown", "intersection", "arterial", "suburban")
PLACEMENT_RIGS = ("ego", "pole", "drone")


def placement_frames(cameras: int, presets=PLACEMENT_PRESETS):
    """(scene, seed, index) of `cameras` frames spread evenly over `presets`, the k-th preset's
    city with seed k + 1 and its frames 0, 1, ...: the scenes `omnigen render` draws."""
    from omnigen.scenes.generate import SceneGenerator

    for k, preset in enumerate(presets):
        n = cameras // len(presets) + (k < cameras % len(presets))
        gen = SceneGenerator(preset, k + 1)
        for i in range(n):
            yield gen.frame(k + 1, i), k + 1, i


def placement_counts(rig_names=PLACEMENT_RIGS, cameras: int = 100, presets=PLACEMENT_PRESETS) -> dict[str, dict]:
    """Per rig: cameras drawn, how many pass its placement check (ego: over a driving lane looking
    along it; rigs with a near_distance: at most max_near_share of the image nearer), the worst
    near share, and the mean and most draws a camera took."""
    from omnigen.rigs.rig import load_rig
    from omnigen.rigs.sampling import Obstacles, lane_problem, near_share, rig_rng, sample_camera

    rigs = {name: load_rig(name) for name in rig_names}
    out = {name: {"cameras": 0, "passed": 0, "worst_share": 0.0, "tries": []} for name in rig_names}
    for scene, seed, index in placement_frames(cameras, presets):
        obstacles = Obstacles(scene)
        for name, rig in rigs.items():
            cam = sample_camera(rig, scene, rig_rng(seed, index), *rig.resolution, obstacles)
            row = out[name]
            row["cameras"] += 1
            row["tries"].append(cam.tries)
            if rig.near_distance > 0:
                share = near_share(scene, cam, rig.near_distance)
                row["worst_share"] = max(row["worst_share"], share)
                row["passed"] += share <= rig.max_near_share
            else:
                row["passed"] += lane_problem(rig, scene.city, cam) is None
    for name, row in out.items():
        tries = row.pop("tries")
        row.update(mean_tries=sum(tries) / max(len(tries), 1), most_tries=max(tries, default=0),
                   view=rigs[name].view, near_distance=rigs[name].near_distance, max_near_share=rigs[name].max_near_share)
    return out


def placement_line(name: str, row: dict) -> str:
    """One rig's count as the benchmark prints it."""
    n, ok = row["cameras"], row["passed"]
    if row["near_distance"] > 0:
        said = (f"{ok}/{n} with at most {row['max_near_share']:.0%} of pixels within {row['near_distance']:g} m "
                f"(worst {row['worst_share']:.1%})")
    else:
        said = f"{ok}/{n} cameras over a drivable lane, looking along it"
    return f"{name}: {said}; {row['mean_tries']:.2f} draws a camera on average, at most {row['most_tries']}"


def placement_main(cameras: int) -> int:
    t0 = time.perf_counter()
    counts = placement_counts(cameras=cameras)
    print(f"placement checks: {cameras} cameras a rig over {', '.join(PLACEMENT_PRESETS)} (seeds 1-{len(PLACEMENT_PRESETS)}), "
          f"{time.perf_counter() - t0:.1f} s")
    for name, row in counts.items():
        print(placement_line(name, row))
    return 0 if all(row["passed"] == row["cameras"] for row in counts.values()) else 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="downtown")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--no-raster", action="store_true")
    ap.add_argument("--placement", action="store_true", help="count the rigs' placement checks instead (issue 45)")
    ap.add_argument("--cameras", type=integer(1, 100_000), default=100, help="--placement: cameras a rig")
    args = ap.parse_args()
    if args.placement:
        return placement_main(args.cameras)

    t0 = time.perf_counter()
    from omnigen.scenes.generate import SceneGenerator  # noqa: E402

    gen = SceneGenerator(args.preset, args.seed)
    scene = gen.frame(args.seed, 0)
    t_desc = time.perf_counter() - t0
    ti = time.perf_counter()
    from omnigen.scenes.blender_backend import BlenderScene  # noqa: E402

    t1 = time.perf_counter()
    t_import = t1 - ti
    bs = BlenderScene(scene)
    t_blender = time.perf_counter() - t1
    total = time.perf_counter() - t0
    peak = peak_mb()
    faces = sum(len(m.faces) for o in bs.objects.values() for m in o.parts.values())

    print(f"machine: {platform.machine()} {platform.processor() or ''} python {platform.python_version()}")
    print(f"city: preset {args.preset}, seed {args.seed}: {len(scene.city.buildings)} buildings, {len(scene.city.furniture)} furniture, "
          f"{len(scene.agents)} agents, {len(bs.objects)} objects, {faces} triangles")
    print(f"description (city + frame 0, imports included): {t_desc:6.2f} s")
    print(f"import bpy:                                      {t_import:6.2f} s")
    print(f"Blender scene (meshes, materials, sky, weather): {t_blender:6.2f} s")
    print(f"default city build, total:                       {total:6.2f} s   (target < 10 s) {'OK' if total < 10 else 'OVER'}")
    print(f"peak resident memory:                            {peak:6.0f} MB  (target < 2048 MB) {'OK' if peak < 2048 else 'OVER'}")

    times_desc, times_update = [], []
    for i in range(1, args.frames + 1):
        a = time.perf_counter()
        frame = gen.frame(args.seed, i)
        b = time.perf_counter()
        bs.update(frame)
        c = time.perf_counter()
        times_desc.append(b - a)
        times_update.append(c - b)
    if times_desc:
        print(f"per frame, {args.frames} frames: re-randomise {1000 * sum(times_desc) / len(times_desc):6.0f} ms, "
              f"Blender update {1000 * sum(times_update) / len(times_update):6.0f} ms; peak now {peak_mb():.0f} MB")

    if not args.no_raster:
        import numpy as np

        from omnigen.camera import Camera, intrinsics_from_fov
        from omnigen.scenes.raster_backend import RasterScene

        a = time.perf_counter()
        rs = RasterScene(scene)
        b = time.perf_counter()
        K = intrinsics_from_fov(math.radians(70), 640, 640)
        eye = np.array([-90.0, -100.0, 110.0])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        rs.render(Camera(K, R, -R @ eye, 640, 640))  # first render uploads the meshes to GL
        c = time.perf_counter()
        n = 3
        for _ in range(n):
            rs.render(Camera(K, R, -R @ eye, 640, 640))
        d = time.perf_counter()
        print(f"raster preview: build {b - a:5.2f} s, first 640x640 frame {c - b:5.2f} s, then {(d - c) / n:5.2f} s a frame "
              f"(RGB + depth + instance mask + atmosphere)")
    return 0 if total < 10 and peak < 2048 else 1


if __name__ == "__main__":
    sys.exit(main())
