"""Plausible KITTI-format trees and archives, for tests, the benchmark and `make demo`.

Nothing here is real data: each frame gets a random P2 (with camera 2's offset in its last
column, as KITTI's), upright cars, pedestrians and cyclists standing on a slightly tilted road in
front of the camera, labels whose 2D boxes are the projected cuboids' extents clipped to the image
(as KITTI's are, to about a pixel), a DontCare region or two and a tiny PNG. One numpy Generator per
frame, seeded from (seed, frame index), so any frame can be regenerated alone and a tree is the same
however it is produced.

    python -m omnigen.converters.kitti_fixture OUT --frames 8 [--seed 0] [--split training] [--zips]
"""

from __future__ import annotations

import argparse
import math
import zipfile
from pathlib import Path

import numpy as np
from PIL import Image

from omnigen.converters.kitti import ARCHIVES, folders_for
from omnigen.formats.kitti import box_from_kitti, kitti_alpha
from omnigen.geometry import project_points

KITTI_SIZE = (1242, 375)
KITTI_FOCAL = 721.5377
CLASSES = (  # name, probability, (h, w, l) mean, (h, w, l) spread
    ("Car", 0.7, (1.53, 1.63, 3.88), (0.15, 0.10, 0.40)),
    ("Pedestrian", 0.2, (1.76, 0.66, 0.84), (0.10, 0.08, 0.20)),
    ("Cyclist", 0.1, (1.74, 0.60, 1.76), (0.08, 0.06, 0.15)),
)
TR_IMU_TO_VELO = np.array([[0.9999976, 0.0007553071, -0.002035826, -0.8086759],
                           [-0.0007854027, 0.9998898, -0.01482298, 0.3195559],
                           [0.002024406, 0.01482454, 0.9998881, -0.7997231]])


def frame_rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng([seed, index])


def random_projection(rng: np.random.Generator, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(K, camera 2's offset t): KITTI's intrinsics scaled to the image, P2 = K [I | t]."""
    f = KITTI_FOCAL * width / KITTI_SIZE[0] * rng.uniform(0.97, 1.03)
    K = np.array([[f, 0.0, (width - 1) / 2 + rng.uniform(-0.02, 0.02) * width],
                  [0.0, f, height * rng.uniform(0.44, 0.48)],
                  [0.0, 0.0, 1.0]])
    t = np.array([0.06, -0.0015, 0.0035]) + rng.normal(0.0, [0.002, 0.0005, 0.001])
    return K, t


def _corner_box(corners: np.ndarray, K: np.ndarray) -> np.ndarray:
    uv, _ = project_points(K, corners)
    return np.concatenate([uv.min(axis=0), uv.max(axis=0)])


def random_object(rng: np.random.Generator, K: np.ndarray, t: np.ndarray, width: int, height: int,
                  road: tuple[float, float]) -> str | None:
    """One label line for an object standing on the road in front of the camera, or None if it
    landed outside the image (the caller draws again)."""
    probs = [c[1] for c in CLASSES]
    name, _, mean, spread = CLASSES[rng.choice(len(CLASSES), p=probs)]
    h, w, l = np.maximum(rng.normal(mean, spread), 0.3)
    z = rng.uniform(4.0, 45.0)
    x = rng.uniform(-0.8, 0.8) * z
    cam_height, pitch = road
    y = cam_height + z * math.tan(pitch)  # bottom centre on a road pitched by `pitch`
    ry = rng.uniform(-math.pi, math.pi)
    box = box_from_kitti(h, w, l, x, y, z, ry, t)
    full = _corner_box(box.corners(), K)
    clipped = np.clip(full, [0, 0, 0, 0], [width - 1, height - 1, width - 1, height - 1])
    if clipped[2] - clipped[0] <= 0 or clipped[3] - clipped[1] <= 0:
        return None
    area = lambda b: (b[2] - b[0]) * (b[3] - b[1])  # noqa: E731
    truncated = float(np.clip(1.0 - area(clipped) / area(full), 0.0, 1.0))
    occluded = int(rng.choice(4, p=[0.55, 0.25, 0.15, 0.05]))
    alpha = kitti_alpha(ry, x, z)
    values = [truncated, occluded, alpha, *clipped, h, w, l, x, y, z, ry]
    return f"{name} {values[0]:.2f} {values[1]:d} " + " ".join(f"{v:.2f}" for v in values[2:])


def random_dont_care(rng: np.random.Generator, width: int, height: int) -> str:
    x1, y1 = rng.uniform(0, width * 0.8), rng.uniform(height * 0.3, height * 0.6)
    x2, y2 = x1 + rng.uniform(1, width * 0.2), y1 + rng.uniform(1, height * 0.2)
    return f"DontCare -1 -1 -10 {x1:.2f} {y1:.2f} {min(x2, width - 1):.2f} {min(y2, height - 1):.2f} -1 -1 -1 -1000 -1000 -1000 -10"


def calib_text(K: np.ndarray, t: np.ndarray) -> str:
    """All seven lines of a KITTI calib file; P2 = K [I | t] carries camera 2's offset."""
    def row(name: str, m: np.ndarray) -> str:
        return f"{name}: " + " ".join(f"{v:.12e}" for v in np.asarray(m).ravel())
    P = lambda offset: np.hstack([K, (K @ offset)[:, None]])  # noqa: E731
    velo = np.array([[0.0, -1.0, 0.0, -0.004], [0.0, 0.0, -1.0, -0.076], [1.0, 0.0, 0.0, -0.272]])
    return "\n".join([
        row("P0", P(np.zeros(3))), row("P1", P(np.array([-0.537, 0.0, 0.0]))), row("P2", P(t)),
        row("P3", P(t + np.array([-0.537, 0.0, 0.0]))), row("R0_rect", np.eye(3)),
        row("Tr_velo_to_cam", velo), row("Tr_imu_to_velo", TR_IMU_TO_VELO),
    ]) + "\n\n"


def write_frame(root: Path, index: int, seed: int, image_size: tuple[int, int], split: str) -> None:
    """Image, calib and (training) label of frame `index`, from its own Generator."""
    rng = frame_rng(seed, index)
    width = image_size[0] - int(rng.integers(0, 3))  # KITTI's sizes vary by a few pixels too
    height = image_size[1] - int(rng.integers(0, 2))
    K, t = random_projection(rng, width, height)
    road = (rng.uniform(1.55, 1.75), math.radians(rng.uniform(-1.5, 1.5)))
    kid = f"{index:06d}"
    colour = tuple(int(c) for c in rng.integers(0, 256, 3))
    Image.new("RGB", (width, height), colour).save(root / "image_2" / f"{kid}.png", compress_level=1)
    (root / "calib" / f"{kid}.txt").write_text(calib_text(K, t))
    if split != "training":
        return
    lines = []
    for _ in range(min(int(rng.poisson(5.0)), 15)):
        for _attempt in range(10):
            line = random_object(rng, K, t, width, height, road)
            if line is not None:
                lines.append(line)
                break
    lines += [random_dont_care(rng, width, height) for _ in range(int(rng.integers(0, 3)))]
    (root / "label_2" / f"{kid}.txt").write_text("".join(f"{line}\n" for line in lines))


def write_kitti_tree(root: str | Path, n_frames: int, seed: int = 0, image_size: tuple[int, int] = (124, 38),
                     split: str = "training") -> Path:
    """Write root/<split>/{image_2,calib[,label_2]} with n_frames frames; returns root/<split>.

    The default image is a tenth of KITTI's, with K scaled to match, so geometry stays KITTI-like
    while the PNGs are a few hundred bytes.
    """
    split_root = Path(root) / split
    for folder in folders_for(split):
        (split_root / folder).mkdir(parents=True, exist_ok=True)
    for index in range(n_frames):
        write_frame(split_root, index, seed, image_size, split)
    return split_root


def write_kitti_zips(tree_root: str | Path, out_dir: str | Path) -> dict[str, Path]:
    """The three official archives (data_object_{image_2,label_2,calib}.zip) of a KITTI tree.

    Members are named as in the official archives (`training/image_2/000000.png`); images are
    stored, text is deflated.
    """
    tree_root, out_dir = Path(tree_root), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = {}
    for folder, archive in ARCHIVES.items():
        path = out_dir / archive
        method = zipfile.ZIP_STORED if folder == "image_2" else zipfile.ZIP_DEFLATED
        with zipfile.ZipFile(path, "w", compression=method) as zf:
            for split in ("training", "testing"):
                source = tree_root / split / folder
                if source.is_dir():
                    for file in sorted(source.iterdir()):
                        zf.write(file, f"{split}/{folder}/{file.name}")
        written[folder] = path
    return written


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Write a plausible KITTI-format tree (not real data).")
    p.add_argument("out", type=Path)
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--split", choices=("training", "testing"), default="training")
    p.add_argument("--zips", action="store_true", help="also write the three official archives into OUT")
    args = p.parse_args(argv)
    write_kitti_tree(args.out, args.frames, args.seed, split=args.split)
    if args.zips:
        write_kitti_zips(args.out, args.out)
    print(f"wrote {args.frames} {args.split} frames under {args.out / args.split}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
