"""Realism figures for docs/realism.md: rendered frames beside the real ones, with their histograms.

Why: numbers alone (benchmarks/bench_realism.py) do not show what a reader should look for; a
rendered ego frame beside a real KITTI frame does. Two figures:

- docs/images/realism-ego.png: a rendered ego frame beside a KITTI frame (each the frame of its set
  whose luminance std is nearest the set's median, so neither is picked for looks), and below them
  the luminance and R, G, B histograms of both sets (averaged over frames).
- docs/images/realism-pole.png: a rendered pole frame beside the DAIR-V2X sample as far as it goes:
  the sample has a label and no image, so its objects are drawn from above (the virtual-LiDAR frame,
  x forward, y left) beside the pole frame's own objects (camera frame moved onto the ground plane);
  below, the pole frames' histograms against KITTI's (the only real photographs here) and the
  distances to the camera against DAIR-V2X's.

The renders are bench_realism's (same work folder, reused while the sources are unchanged). Each
PNG is written at 80 dpi and reduced to 256 colours so that it stays well under 400 KB.

    .venv/bin/python benchmarks/realism_figure.py [--frames 12] [--size 640] [--work runs/realism]
        [--seed 0] [--scene NAME] [--realdata ../shared/realdata] [--out-dir docs/images]
"""

from __future__ import annotations

import argparse
import io
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks import bench_realism as br  # noqa: E402

DPI = 80
CLASS_COLOURS = {"car": "tab:blue", "van": "tab:cyan", "truck": "tab:orange", "bus": "tab:red", "tram": "tab:brown",
                 "pedestrian": "tab:green", "cyclist": "tab:olive", "motorcyclist": "tab:purple",
                 "tricyclist": "tab:pink", "barrow": "tab:gray", "traffic_cone": "gold", "misc": "black"}


def representative(s: br.SetStats) -> int:
    """Index of the frame whose luminance std is nearest the set's median (as the benchmark measured
    them)."""
    return int(np.argmin(np.abs(np.asarray(s.lum_std_per_frame) - s.lum_std)))


def save_small(fig, path: Path) -> int:
    """Save a figure as a 256-colour PNG (photographs in it dither acceptably); returns its bytes."""
    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    buf.seek(0)
    with Image.open(buf) as im:
        small = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    path.parent.mkdir(parents=True, exist_ok=True)
    small.save(path, optimize=True)
    return path.stat().st_size


def plot_histograms(ax, sets: list[tuple[br.SetStats, str]], title: str) -> None:
    """Luminance (black) and R, G, B histograms of each set; the first set solid, the next dashed."""
    centres = br.bin_centres()
    for s, style in sets:
        ax.plot(centres, s.hist_lum, color="black", ls=style, lw=1.6, label=f"{s.name} luminance")
        for c, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
            ax.plot(centres, s.hist_rgb[c], color=colour, ls=style, lw=0.9)
    ax.set_xlim(0, 255)
    ax.set_xlabel("8-bit value (R, G, B in colour)")
    ax.set_ylabel("fraction of pixels")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)


def show_image(ax, im: np.ndarray, title: str) -> None:
    ax.imshow(im)
    ax.set_title(title, fontsize=9)
    ax.axis("off")


def ego_figure(ego: list[np.ndarray], kitti: list[np.ndarray] | None, k: br.SetStats | None, path: Path) -> int:
    """The ego figure; `k` is set_stats of the `kitti` frames (None without them)."""
    import matplotlib.pyplot as plt

    e = br.set_stats("rendered ego", ego)
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), gridspec_kw={"height_ratios": [1.3, 1]})
    i = representative(e)
    show_image(axes[0, 0], ego[i], f"rendered ego (raster), frame {i}: lum std {e.lum_std_per_frame[i]:.1f}")
    if kitti:
        j = representative(k)
        show_image(axes[0, 1], kitti[j], f"KITTI training frame {j}: lum std {k.lum_std_per_frame[j]:.1f}")
        plot_histograms(axes[1, 0], [(e, "-"), (k, "--")], "luminance and R, G, B: rendered (solid), KITTI (dashed)")
        d = br.compare(e, k)
        axes[1, 1].axis("off")
        rows = [("", "rendered ego", "KITTI"), ("frames", str(e.frames), str(k.frames)),
                ("median luminance std", f"{e.lum_std:.1f}", f"{k.lum_std:.1f}"),
                ("median luminance mean", f"{e.lum_mean:.1f}", f"{k.lum_mean:.1f}"),
                ("median edge density", f"{e.edge_density:.3f}", f"{k.edge_density:.3f}"),
                ("median colourfulness", f"{e.colourfulness:.1f}", f"{k.colourfulness:.1f}"),
                ("luminance hist. intersection", f"{d['lum_intersection']:.3f}", ""),
                ("luminance EMD (grey levels)", f"{d['lum_emd']:.1f}", "")]
        tab = axes[1, 1].table(cellText=[list(r) for r in rows], loc="center", cellLoc="left", colWidths=[0.56, 0.22, 0.22])
        tab.auto_set_font_size(False)
        tab.set_fontsize(8)
        tab.scale(1, 1.4)
    else:
        axes[0, 1].axis("off")
        axes[0, 1].text(0.5, 0.5, "no KITTI frames in ../shared/realdata", ha="center", va="center")
        plot_histograms(axes[1, 0], [(e, "-")], "luminance and R, G, B: rendered ego")
        axes[1, 1].axis("off")
    fig.tight_layout()
    size = save_small(fig, path)
    plt.close(fig)
    return size


def ground_view(record: dict) -> list[tuple[str, float, float, float, float, float]]:
    """A synthetic frame's objects from above: (class, forward, left, yaw, l, w) in metres, on the
    ground plane under the camera, forward along the camera's view projected onto the ground."""
    n = np.asarray(record["ground_plane"]["normal"], dtype=np.float64)  # the contract's: unit, pointing up
    n = n / np.linalg.norm(n)
    z = np.array([0.0, 0.0, 1.0])
    fwd = z - (z @ n) * n
    fwd /= np.linalg.norm(fwd)
    left = np.cross(n, fwd)
    out = []
    for o in record["objects"]:
        c = np.asarray(o["box3d"]["center"], dtype=np.float64)
        heading = np.asarray(o["box3d"]["rotation"], dtype=np.float64)[:, 0]
        l, w, _ = o["box3d"]["dims"]
        out.append((o["category"], float(c @ fwd), float(c @ left), math.atan2(heading @ left, heading @ fwd), l, w))
    return out


def dair_view(labels: list) -> list[tuple[str, float, float, float, float, float]]:
    """The DAIR-V2X label's objects (bench_realism.dair_labels: the converter's reading) from above
    in the virtual-LiDAR frame (x forward, y left; the yaw about +z, 0 along +x, as
    omnigen.formats.dair reads it)."""
    return [(o.category, float(o.center[0]), float(o.center[1]), o.yaw, float(o.lwh[0]), float(o.lwh[1]))
            for o in labels]


def draw_top(ax, objs, fill: bool, label: str) -> None:
    """Objects as rectangles from above (their cuboids' top corners 0-3, omnigen.geometry's):
    forward up the page, left to the left."""
    from matplotlib.patches import Polygon

    from omnigen.geometry import cuboid_corners, rot_z

    for cat, x, y, yaw, l, w in objs:
        corners = cuboid_corners(np.array([x, y, 0.0]), np.array([l, w, 0.0]), rot_z(yaw))[:4, :2]
        pts = [(-c[1], c[0]) for c in corners]  # page x = -left, page y = forward
        colour = CLASS_COLOURS.get(cat, "black")
        ax.add_patch(Polygon(pts, closed=True, fill=fill, facecolor=colour, edgecolor=colour, lw=1.0, alpha=0.8))
    ax.plot([], [], "s", mfc="gray" if fill else "none", mec="gray", ls="", label=label)


def pole_figure(pole: list[np.ndarray], records: list[dict], k: br.SetStats | None, labels: list | None,
                distances: np.ndarray, path: Path, label_names: tuple[str, ...] | list[str] = ()) -> int:
    """The pole figure; `k` is KITTI's set_stats, `labels` the DAIR-V2X sample's (dair_labels),
    read from the label files `label_names` (their stems, for the legend)."""
    import matplotlib.pyplot as plt

    p = br.set_stats("rendered pole", pole)
    fig, axes = plt.subplots(2, 2, figsize=(11, 8), gridspec_kw={"height_ratios": [1.2, 1]})
    i = representative(p)
    show_image(axes[0, 0], pole[i], f"rendered pole (raster), frame {i}: lum std {p.lum_std_per_frame[i]:.1f}")
    ax = axes[0, 1]
    ours, theirs = ground_view(records[i]), (dair_view(labels) if labels is not None else [])
    draw_top(ax, ours, fill=False, label=f"pole frame {i} (outline)")
    if labels is not None:
        names = ", ".join(label_names) or "sample"
        draw_top(ax, theirs, fill=True, label=f"DAIR-V2X-C {names} label{'s' if len(label_names) > 1 else ''} (filled)")
    ax.plot([0], [0], "k^", ms=8, label="camera / LiDAR")
    everything = ours + theirs
    reach = max([10.0] + [abs(o[1]) + o[4] for o in everything] + [2 * abs(o[2]) + o[4] for o in everything])
    ax.set_xlim(-0.8 * reach, reach / 2)  # room on the left for the legend
    ax.set_ylim(-5, reach)
    ax.set_aspect("equal")
    ax.set_xlabel("metres to the right")
    ax.set_ylabel("metres forward")
    seen = sorted({o[0] for o in everything})
    for cat in seen:
        ax.plot([], [], "s", color=CLASS_COLOURS.get(cat, "black"), ls="", label=cat)
    ax.legend(fontsize=6, loc="lower left")
    ax.set_title("objects from above: the pole frame and the DAIR-V2X label (it has no image)", fontsize=9)
    if k is not None:
        plot_histograms(axes[1, 0], [(p, "-"), (k, "--")],
                        "pole (solid) against KITTI (dashed; no roadside photo in the sample)")
    else:
        plot_histograms(axes[1, 0], [(p, "-")], "luminance and R, G, B: rendered pole")
    ax = axes[1, 1]
    bins = np.linspace(0, 200, 21)
    ax.hist(np.clip(distances, 0, 200), bins=bins, density=True, alpha=0.6, label=f"rendered pole ({len(distances)} objects)")
    if labels is not None:
        dd = br.dair_objects(labels).values("distance")
        ax.hist(np.clip(dd, 0, 200), bins=bins, density=True, histtype="step", lw=2, color="black",
                label=f"DAIR-V2X sample ({len(dd)} objects)")
    ax.set_xlabel("distance to the camera (m; DAIR: to the LiDAR)")
    ax.set_ylabel("density")
    ax.legend(fontsize=7)
    ax.set_title("distances", fontsize=9)
    fig.tight_layout()
    size = save_small(fig, path)
    plt.close(fig)
    return size


def main(argv: list[str] | None = None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    br.add_render_arguments(ap)
    ap.add_argument("--out-dir", default=str(ROOT / "docs" / "images"))
    args = ap.parse_args(argv)
    work, out = Path(args.work), Path(args.out_dir)
    stamp = br.sources_hash()
    kitti_root, dair, notes = br.real_sources(Path(args.realdata))
    for n in notes:
        print(n)
    try:
        ds = {rig: br.rig_dataset(work, rig, args.frames, args.size, args.seed, stamp, args.scene) for rig in ("ego", "pole")}
    except RuntimeError as exc:
        print(f"realism_figure: {exc}", file=sys.stderr)
        return 1
    kitti = br.kitti_images(kitti_root, args.size) if kitti_root else None
    k = br.set_stats("KITTI", kitti) if kitti else None
    size = ego_figure(br.dataset_images(ds["ego"]), kitti, k, out / "realism-ego.png")
    print(f"wrote {out / 'realism-ego.png'} ({size / 1024:.0f} KB)")
    records = br.dataset_records(ds["pole"])
    labels = br.dair_labels(dair) if dair is not None else None
    names = [p.stem for p in br.dair_label_files(dair)] if dair is not None else []
    size = pole_figure(br.dataset_images(ds["pole"]), records, k, labels,
                       br.synthetic_objects("pole", records).values("distance"), out / "realism-pole.png", names)
    print(f"wrote {out / 'realism-pole.png'} ({size / 1024:.0f} KB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
