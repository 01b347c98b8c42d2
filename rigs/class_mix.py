"""Which classes a preset's frames hold, and how big its cars and people are: issue 26's figure
("10 frames, 6 drone + 4 pole, 320 x 240, raster, default preset: at least 6 classes including
traffic cones; median car length 3.6-4.9 m; pedestrians 1.5-1.95 m tall").

    from omnigen.rigs.class_mix import class_counts
    mix = class_counts("downtown", seeds=(0,))               # geometry only: no renderer, ~1 s
    mix = class_counts("downtown", seeds=(0,), render=True)   # the raster frames' annotations
    print(mix.table())

Two ways to count, same frames (frame i of seed s: `SceneGenerator(preset, s).frame(s, i)`, the
camera from the rig's own stream, as `omnigen render` draws them):
- `render=False` (the test's): an agent counts when its projected cuboid, clipped to the image,
  covers at least SEEN_BOX_PIXELS (twice the annotator's MIN_VISIBLE_PIXELS: a silhouette fills
  about half its cuboid's box) and it stands in front of the camera within MAX_DISTANCE. Nothing
  hides anything, so it counts at least what a render annotates, a little more in dense streets.
- `render=True`: `omnigen render --backend raster` into a temporary folder and the records'
  objects, i.e. what the dataset holds (needs the EGL raster backend).

Randomness: none of its own; everything follows from (preset, seed, frame index).
"""

from __future__ import annotations

import statistics
import tempfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from omnigen.rigs.annotate import MIN_VISIBLE_PIXELS
from omnigen.rigs.rig import load_rig
from omnigen.rigs.sampling import MAX_DISTANCE, Obstacles, projected_agents, rig_rng, sample_camera
from omnigen.scenes.generate import SceneGenerator

SEEN_BOX_PIXELS = 2 * MIN_VISIBLE_PIXELS
DEFAULT_RIGS = (("drone", 6), ("pole", 4))


@dataclass
class ClassMix:
    """Objects per class over a set of frames, and the sizes the issue's figure checks."""

    frames: int = 0
    objects: Counter = field(default_factory=Counter)  # class -> objects
    frames_with: Counter = field(default_factory=Counter)  # class -> frames holding at least one
    car_lengths: list[float] = field(default_factory=list)
    pedestrian_heights: list[float] = field(default_factory=list)
    how: str = "geometry"

    @property
    def classes(self) -> list[str]:
        return sorted(self.objects)

    @property
    def median_car_length(self) -> float | None:
        return statistics.median(self.car_lengths) if self.car_lengths else None

    def add_frame(self, categories: list[str], dims: list[tuple[float, float, float]]) -> None:
        self.frames += 1
        self.objects.update(categories)
        self.frames_with.update(set(categories))
        self.car_lengths += [d[0] for c, d in zip(categories, dims) if c == "car"]
        self.pedestrian_heights += [d[2] for c, d in zip(categories, dims) if c == "pedestrian"]

    def table(self) -> str:
        """A plain text table: class, objects, frames holding it; then the size figures."""
        lines = [f"{'class':<14} {'objects':>8} {'frames':>7}  ({self.frames} frames, {self.how})"]
        for c in sorted(self.objects, key=lambda k: (-self.objects[k], k)):
            lines.append(f"{c:<14} {self.objects[c]:>8} {self.frames_with[c]:>7}")
        car = self.median_car_length
        lines.append(f"classes: {len(self.objects)}; traffic_cone: {'yes' if 'traffic_cone' in self.objects else 'no'}")
        lines.append(f"median car length: {car:.2f} m" if car is not None else "median car length: no cars")
        if self.pedestrian_heights:
            lines.append(f"pedestrian height: {min(self.pedestrian_heights):.2f} to {max(self.pedestrian_heights):.2f} m "
                         f"(median {statistics.median(self.pedestrian_heights):.2f})")
        return "\n".join(lines)


def seen_agents(scene, cam) -> list:
    """The agents a camera would annotate by geometry alone (see the module doc)."""
    depth, bbox = projected_agents(scene, cam)
    w = np.minimum(bbox[:, 2], cam.width) - np.maximum(bbox[:, 0], 0.0)
    h = np.minimum(bbox[:, 3], cam.height) - np.maximum(bbox[:, 1], 0.0)
    ok = (depth > 0.5) & (depth < MAX_DISTANCE) & (np.nan_to_num(w) > 0) & (np.nan_to_num(h) > 0)
    ok &= np.nan_to_num(w * h) >= SEEN_BOX_PIXELS
    return [a for a, keep in zip(scene.agents, ok) if keep]


def class_counts(preset: str = "downtown", seeds=(0,), rigs=DEFAULT_RIGS, width: int = 320, height: int = 240,
                 render: bool = False) -> ClassMix:
    """Classes in the frames 0..n-1 of each (rig, n) in `rigs` for each seed (the issue's figure:
    6 drone + 4 pole frames of seed 0 at 320 x 240, downtown). `preset` may be a mix."""
    if render:
        return _rendered_counts(preset, seeds, rigs, width, height)
    mix = ClassMix()
    for seed in seeds:
        gen = SceneGenerator(preset, seed)
        for rig_name, n in rigs:
            rig = load_rig(rig_name)
            for i in range(n):
                scene = gen.frame(seed, i)
                cam = sample_camera(rig, scene, rig_rng(seed, i), width, height, Obstacles(scene))
                seen = seen_agents(scene, cam)
                mix.add_frame([a.category for a in seen], [a.dims for a in seen])
    return mix


def _rendered_counts(preset: str, seeds, rigs, width: int, height: int) -> ClassMix:
    from omnigen.dataset import Dataset
    from omnigen.rigs.render import Renderer, RenderJob

    mix = ClassMix(how="raster render")
    with tempfile.TemporaryDirectory(prefix="class-mix-") as tmp:
        for seed in seeds:
            for rig_name, n in rigs:
                out = Path(tmp) / f"{rig_name}-s{seed}"
                Renderer(RenderJob(rig=rig_name, frames=n, out=out, seed=seed, scene=preset, width=width, height=height,
                                   backend="raster", durable=False)).run(show_progress=False)
                for rec in Dataset.open(out):
                    mix.add_frame([o.category for o in rec.objects], [tuple(o.box.dims) for o in rec.objects])
    return mix


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description="classes, car lengths and pedestrian heights of a preset's frames")
    ap.add_argument("--scene", default="downtown", help="preset, TOML path or mix (omnigen render --scene)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--drone", type=int, default=6, help="drone frames per seed")
    ap.add_argument("--pole", type=int, default=4, help="pole frames per seed")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--render", action="store_true", help="render with the raster backend and count the annotations")
    args = ap.parse_args(argv)
    rigs = (("drone", args.drone), ("pole", args.pole))
    print(class_counts(args.scene, args.seeds, rigs, args.width, args.height, args.render).table())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
