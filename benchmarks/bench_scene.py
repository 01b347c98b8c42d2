"""Default city build time and peak memory: description plus Blender scene (targets: < 10 s, < 2 GB).

Also prints, for issue 6's budget, what a frame re-randomisation costs (new agents, weather and
lighting drawn, and the Blender scene updated in place) and the raster preview's build and
render times. Every figure is measured in this process, from a cold start (imports included in
the first build, as a user's first command would pay them).

    .venv/bin/python benchmarks/bench_scene.py [--preset downtown] [--seed 0] [--frames 5] [--no-raster]
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


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="downtown")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--no-raster", action="store_true")
    args = ap.parse_args()

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
