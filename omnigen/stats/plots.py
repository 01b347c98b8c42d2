"""The report's figures, drawn with matplotlib from stats.json alone.

Why from the JSON and not from the dataset: everything a figure shows is then a number in
stats.json (histogram counts, quantiles, heatmap cells), so the page and the file can never
disagree and a figure can be redrawn from a saved report. Box plots are drawn from stored
quantiles (whiskers at the 5th and 95th percentiles, box at the quartiles).

matplotlib is used through `Figure` objects, never pyplot: no global state, no GUI backend, the
Agg canvas only. Each figure is written as a PNG beside index.html.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any, Callable

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from omnigen.files import atomic_write_bytes
from omnigen.stats.compute import OCCLUSION_LEVEL_NAMES

DPI = 80
BLUE, ORANGE, GREEN, RED, GREY = "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#7f7f7f"


def _fig(w: float, h: float, ncols: int = 1, nrows: int = 1, left: float = 0.7, right: float = 0.2,
         bottom: float = 0.55, top: float = 0.35, wspace: float = 0.3, hspace: float = 0.5) -> tuple[Figure, Any]:
    """A figure with fixed margins in inches (matplotlib's constrained layout doubled the drawing time)."""
    fig = Figure(figsize=(w, h), dpi=DPI)
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        wspace=wspace, hspace=hspace)
    return fig, fig.subplots(nrows, ncols, squeeze=False)


def _save(fig: Figure, path: Path) -> None:
    """Drawn into memory, then written by temporary name and rename: savefig(path) would write
    through whatever file the name already is, a hard link into another tree included."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    atomic_write_bytes(path, buf.getvalue(), durable=False)  # stats.json, written last, is the durable one


def _log_x(ax) -> None:
    """A log x axis labelled 1 2 5 10 20 ... in plain numbers (no 10^k, no crowded minor labels)."""
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())


def _bars_from_hist(ax, h: dict[str, Any], color: str = BLUE, log_x: bool = False) -> None:
    edges = np.asarray(h["edges"], dtype=float)
    ax.stairs(h["counts"], edges, fill=True, color=color, alpha=0.8)
    if log_x:
        _log_x(ax)
    ax.set_ylabel("count")


def _hist_or_value(ax, h: dict[str, Any], label: str, color: str = BLUE) -> None:
    """A histogram, or, where every value is the same (a rig's fixed roll, fog off in every frame),
    that value written out: a single bar of a unit-wide axis read as an empty plot."""
    s = h.get("summary") or {}
    if s.get("n") and s.get("min") == s.get("max"):
        _empty(ax, f"{label}:\nall {s['n']} values {s['min']:g}")
        return
    _bars_from_hist(ax, h, color=color)
    ax.set_xlabel(label)


def _empty(ax, text: str = "no data") -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color=GREY)
    ax.set_xticks([])
    ax.set_yticks([])


def _bxp_stats(s: dict[str, Any], label: str) -> dict[str, Any] | None:
    if not s or not s.get("n"):
        return None
    return {"label": label, "med": s["median"], "q1": s["p25"], "q3": s["p75"], "whislo": s["p5"],
            "whishi": s["p95"], "fliers": []}


def _boxplot(ax, by_class: dict[str, dict[str, Any]], order: list[str], xlabel: str, log: bool = False) -> list[str]:
    """Horizontal box plots of the classes in `order` that have data; returns the classes drawn."""
    stats = [b for c in order if c in by_class and (b := _bxp_stats(by_class[c], c)) is not None]
    if not stats:
        _empty(ax)
        return []
    ax.bxp(stats, orientation="horizontal", showfliers=False, patch_artist=True,
           boxprops={"facecolor": "#aec7e8"}, medianprops={"color": RED})
    if log:
        _log_x(ax)
    ax.set_xlabel(xlabel)
    ax.invert_yaxis()
    return [s["label"] for s in stats]


# ---------------------------------------------------------------------------------------------
# One function per figure; each takes a section of stats.json (and the whole stats for context)
# ---------------------------------------------------------------------------------------------


def plot_classes(sec: dict[str, Any], stats: dict[str, Any], path: Path) -> None:
    names = [c for c in stats["classes"] if sec["classes"][c]]
    fig, ax = _fig(6.4, 0.3 * max(len(names), 3) + 0.9, left=1.1)
    ax = ax[0, 0]
    if not names:
        _empty(ax)
    else:
        counts = [sec["classes"][c] for c in names]
        bars = ax.barh(names, counts, color=BLUE)
        ax.bar_label(bars, labels=[f"{n:,}" for n in counts], padding=3, fontsize=8)
        ax.invert_yaxis()
        ax.set_xlabel("objects")
        ax.margins(x=0.15)
    ax.set_title("Objects per class")
    _save(fig, path)


def plot_objects_per_frame(sec: dict[str, Any], stats: dict[str, Any], path: Path) -> None:
    fig, ax = _fig(6.4, 2.6)
    ax = ax[0, 0]
    counts = sec["objects_per_frame"]["counts"]
    if not counts:
        _empty(ax)
    else:
        ax.bar(np.arange(len(counts)), counts, color=BLUE, width=0.9)
        ax.set_xlabel("objects in the frame")
        ax.set_ylabel("frames")
    ax.set_title("Objects per frame")
    _save(fig, path)


def plot_distance(sec: dict[str, Any], stats: dict[str, Any], path: Path) -> None:
    fig, ax = _fig(10, 3.2, ncols=2, wspace=0.4)
    h = sec["distance_m"]
    _bars_from_hist(ax[0, 0], h)
    ax[0, 0].set_xlabel("distance from the camera to the cuboid centre (m)")
    ax[0, 0].set_title("Object distance")
    _boxplot(ax[0, 1], h["by_class"], stats["classes"], "distance (m)")
    ax[0, 1].set_title("Distance per class (5-25-50-75-95 %)")
    _save(fig, path)


def plot_pixel_size(sec: dict[str, Any], stats: dict[str, Any], path: Path) -> None:
    fig, ax = _fig(10, 3.2, ncols=2, wspace=0.4)
    h = sec["pixel_height"]
    _bars_from_hist(ax[0, 0], h, color=GREEN, log_x=True)
    ax[0, 0].set_xlabel("2D box height (px)")
    ax[0, 0].set_title("Object size in pixels")
    _boxplot(ax[0, 1], h["by_class"], stats["classes"], "2D box height (px)", log=True)
    ax[0, 1].set_title("Pixel height per class")
    _save(fig, path)


def plot_dims(sec: dict[str, Any], stats: dict[str, Any], path: Path) -> None:
    names = [c for c in stats["classes"] if c in sec["dims"]]
    fig, ax = _fig(11, 0.3 * max(len(names), 3) + 1.2, ncols=3, left=1.1, wspace=0.08)
    priors = stats["priors"]["classes"]
    for j, (axis, label) in enumerate((("l", "length"), ("w", "width"), ("h", "height"))):
        a = ax[0, j]
        drawn = _boxplot(a, {c: sec["dims"][c][axis] for c in names}, names, f"{label} (m)")
        if drawn:
            ys = np.arange(1, len(drawn) + 1)
            mean = [priors[c]["mean"][j] for c in drawn]
            std = [priors[c]["std"][j] for c in drawn]
            a.errorbar(mean, ys, xerr=2 * np.asarray(std), fmt="D", color=ORANGE, ms=4, capsize=3,
                       label="prior mean ± 2σ")
            _log_x(a)
        if j:
            a.set_yticklabels([])
        a.set_title(f"3D {label} vs prior")
    if names:
        ax[0, 0].legend(loc="lower right", fontsize=7)
    _save(fig, path)


def plot_occlusion(sec: dict[str, Any], stats: dict[str, Any], path: Path) -> None:
    occ = sec["occlusion"]
    fig, ax = _fig(11, 2.8, ncols=3, bottom=0.6, wspace=0.35)
    ax[0, 0].bar(list(OCCLUSION_LEVEL_NAMES), [occ["levels"][k] for k in OCCLUSION_LEVEL_NAMES],
                 color=[GREEN, ORANGE, RED, GREY])
    ax[0, 0].set_title("Occlusion level")
    ax[0, 0].tick_params(axis="x", labelsize=8)
    _bars_from_hist(ax[0, 1], occ["truncation"], color=ORANGE)
    ax[0, 1].set_xlabel("truncation (fraction outside the image)")
    if sum(occ["truncation"]["counts"]):
        ax[0, 1].set_yscale("log")
    ax[0, 1].set_title("Truncation")
    if occ["fraction"]["summary"]["n"]:
        _bars_from_hist(ax[0, 2], occ["fraction"], color=RED)
        ax[0, 2].set_xlabel("occluded fraction (rendered frames)")
    else:
        _empty(ax[0, 2], "no measured occlusion\n(no rendered frames)")
    ax[0, 2].set_title("Occlusion fraction")
    _save(fig, path)


def plot_corners(sec: dict[str, Any], stats: dict[str, Any], path: Path) -> None:
    c = sec["corners"]
    fig, ax = _fig(8, 2.8, bottom=0.7, top=0.5)
    ax = ax[0, 0]
    x = np.arange(len(c["names"]))
    fr = c["fractions"]
    for k, (key, color, label) in enumerate((("in_image", BLUE, "in the image"),
                                             ("occluded_in_image", ORANGE, "in the image, occluded"),
                                             ("behind_camera", RED, "behind the camera"))):
        ax.bar(x + (k - 1) * 0.27, [v or 0 for v in fr[key]], width=0.27, color=color, label=label)
    ax.set_xticks(x, [f"{i}\n{n.replace('_', ' ').replace('front ', 'fr. ').replace('bottom', 'bot.')}"
                      for i, n in enumerate(c["names"])], fontsize=7)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("fraction of objects")
    ax.legend(fontsize=7, ncols=3, loc="upper center", bbox_to_anchor=(0.5, 1.22))
    _save(fig, path)


CAMERA_LABELS = {"height_m": "camera height (m)", "pitch_deg": "pitch below the horizon (°)",
                 "focal_px": "focal length fx (px)", "hfov_deg": "horizontal field of view (°)",
                 "vfov_deg": "vertical field of view (°)"}


def plot_camera(sec: dict[str, Any], stats: dict[str, Any], path: Path) -> None:
    fig, ax = _fig(11, 4.4, ncols=3, nrows=2, wspace=0.35, hspace=0.55)
    cam = sec["camera"]
    for a, key in zip(ax.flat, CAMERA_LABELS):
        if cam[key]["summary"]["n"]:
            _hist_or_value(a, cam[key], CAMERA_LABELS[key])
        else:
            _empty(a, f"{CAMERA_LABELS[key]}:\nnot recorded")
    a = ax[1, 2]
    sizes = dict(sorted(sec["image_sizes"].items(), key=lambda kv: (-kv[1], kv[0])))
    if sizes:
        a.barh(list(sizes), list(sizes.values()), color=GREY)
        a.invert_yaxis()
        a.set_xlabel("frames")
        a.tick_params(axis="y", labelsize=7)
        a.set_title("image sizes", fontsize=9)
    _save(fig, path)


def plot_heatmaps(sec: dict[str, Any], stats: dict[str, Any], path: Path) -> None:
    fig, ax = _fig(10, 4.0, ncols=2, wspace=0.3)
    for a, key, title in ((ax[0, 0], "image", "Object centres in the image (x/W, y/H)"),
                          (ax[0, 1], "ground", "Object footprints on the ground (m)")):
        h = sec["heatmaps"][key]
        counts = np.asarray(h["counts"], dtype=float)
        if counts.sum() == 0:
            _empty(a)
        else:
            xe, ye = np.asarray(h["x_edges"]), np.asarray(h["y_edges"])
            mesh = a.pcolormesh(xe, ye, np.where(counts > 0, counts, np.nan), cmap="viridis",
                                norm=LogNorm(vmin=1, vmax=max(counts.max(), 2)))
            fig.colorbar(mesh, ax=a, label="objects", shrink=0.9)
            a.set_aspect("equal")
        a.set_title(title, fontsize=10)
        if key == "image":
            a.plot([0, 1, 1, 0, 0], [0, 0, 1, 1, 0], color="white" if counts.sum() else GREY, lw=1)
            a.set_xlim(h["x_edges"][0], h["x_edges"][-1])
            a.set_ylim(h["y_edges"][-1], h["y_edges"][0])  # image y grows downwards
        else:
            a.set_xlabel("right of the camera (m)")
            a.set_ylabel("ahead of the camera (m)")
            a.plot([0], [0], marker="^", color=RED, ms=8)
        a.set_facecolor("#f4f4f4")
    _save(fig, path)


def plot_conditions(sec: dict[str, Any], stats: dict[str, Any], path: Path) -> None:
    cond = sec["conditions"]
    items = [(f"{part}: {k}", v) for part in ("weather", "lighting") for k, v in cond[part].items()][:12]
    ncols = 4 if len(items) > 3 else max(len(items), 1)
    nrows = max(1, -(-len(items) // ncols))
    fig, ax = _fig(2.8 * ncols, 2.2 * nrows + 0.3, ncols=ncols, nrows=nrows, left=0.6, bottom=0.7,
                   wspace=0.4, hspace=0.9)
    for a in ax.flat:
        a.set_visible(False)
    for a, (title, v) in zip(ax.flat, items):
        a.set_visible(True)
        if v["kind"] == "categorical":
            a.bar(list(v["counts"]), list(v["counts"].values()), color=BLUE)
            a.tick_params(axis="x", labelsize=7, rotation=30)
        else:
            _hist_or_value(a, v, "value")
        a.set_title(title, fontsize=9)
    if not items:
        ax[0, 0].set_visible(True)
        _empty(ax[0, 0], "no weather or lighting recorded")
    _save(fig, path)


FIGURES: dict[str, tuple[str, Callable[[dict, dict, Path], None]]] = {
    # name: (caption, function); the page shows them in this order
    "classes": ("Class distribution", plot_classes),
    "objects_per_frame": ("Objects per frame", plot_objects_per_frame),
    "distance": ("Object distance", plot_distance),
    "pixel_size": ("Object size in pixels", plot_pixel_size),
    "dims": ("3D dimensions per class against their priors", plot_dims),
    "occlusion": ("Occlusion and truncation", plot_occlusion),
    "corners": ("Per-corner visibility", plot_corners),
    "camera": ("Camera height, pitch, focal length and field of view", plot_camera),
    "heatmaps": ("Where objects are: image and ground plane", plot_heatmaps),
    "conditions": ("Weather and lighting of rendered frames", plot_conditions),
}


def figures_for(sec: dict[str, Any]) -> list[str]:
    """The figures a section has: all, except weather and lighting where no frame was rendered."""
    return [name for name in FIGURES if name != "conditions" or sec["conditions"]["frames"]]


def plot_section(sec: dict[str, Any], stats: dict[str, Any], folder: Path) -> list[Path]:
    """Draw every figure of a section into `folder` as <name>.png; returns the files."""
    files = []
    for name in figures_for(sec):
        FIGURES[name][1](sec, stats, folder / f"{name}.png")
        files.append(folder / f"{name}.png")
    return files
