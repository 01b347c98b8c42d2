"""The raster preview's contrast and brightness per rig, against issue 26's targets.

Renders FRAMES frames per rig with the real pipeline (`omnigen render`'s Renderer, raster backend,
weather and time of day drawn from the preset) into a temporary folder and prints, per rig, the
median over frames of each frame's luminance standard deviation (0.299 R + 0.587 G + 0.114 B on
the 8-bit sRGB PNG, what issue 26 measures), the median mean luminance, and the weather and time
of day of each frame beside its figure. Issue 26's targets: median std >= 55 for ego and pole,
>= 40 for drone (the real KITTI frames: 71-89). The official realism benchmark is
benchmarks/bench_realism.py; this one is the raster backend's quick check.

    .venv/bin/python benchmarks/bench_raster_look.py [--frames 12] [--size 640] [--scene downtown] [--seed 0]
        [--rigs ego,pole,drone] [--keep DIR]

--keep DIR keeps the rendered frames (DIR/<rig>/...) to look at beside real ones.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

TARGETS = {"ego": 55.0, "pole": 55.0, "drone": 40.0}


def luminance_stats(png: Path) -> tuple[float, float]:
    """(std, mean) of a PNG's luminance, 0.299 R + 0.587 G + 0.114 B on its 8-bit sRGB values."""
    from PIL import Image

    y = np.asarray(Image.open(png).convert("RGB"), dtype=np.float64) @ np.array([0.299, 0.587, 0.114])
    return float(y.std()), float(y.mean())


def run_rig(rig: str, frames: int, size: int, scene: str, seed: int, keep: str | None = None) -> list[dict]:
    from omnigen.rigs.render import RenderJob, Renderer

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(keep or tmp) / rig
        job = RenderJob(rig=rig, frames=frames, out=out, seed=seed, scene=scene, width=size, height=size,
                        backend="raster", quality="preview", durable=False)
        r = Renderer(job)
        for i in range(frames):
            r.render_frame(i)
        r.backend.close()
        import json

        for rec in sorted((out / "records").glob("*.json")):
            d = json.loads(rec.read_text())
            std, mean = luminance_stats(out / d["image"])
            syn = d.get("synthetic", {})
            rows.append({"frame": d["frame_id"], "std": std, "mean": mean,
                         "weather": syn.get("weather", {}).get("kind", "?"),
                         "time": syn.get("lighting", {}).get("time_of_day", "?")})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--size", type=int, default=640)
    ap.add_argument("--scene", default="downtown")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rigs", default="ego,pole,drone")
    ap.add_argument("--keep", default=None, help="keep the frames under this folder")
    a = ap.parse_args(argv)
    print(f"{a.frames} frames a rig, {a.size}x{a.size}, scene {a.scene}, seed {a.seed}, raster")
    for rig in a.rigs.split(","):
        rows = run_rig(rig, a.frames, a.size, a.scene, a.seed, a.keep)
        stds = [r["std"] for r in rows]
        med = float(np.median(stds))
        target = TARGETS.get(rig)
        verdict = "" if target is None else (f" (target >= {target:.0f}: {'met' if med >= target else 'not met'})")
        print(f"{rig}: median luminance std {med:.1f}{verdict}, median mean luminance {np.median([r['mean'] for r in rows]):.1f}")
        print("   " + "  ".join(f"{r['std']:.0f} {r['weather']}/{r['time']}" for r in rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
