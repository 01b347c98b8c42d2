"""`omnigen stats`: the report folder, index.html + stats.json + one PNG per figure.

    REPORT/
      index.html            the page (jinja2 template omnigen/stats/templates/index.html.j2)
      stats.json            every number the page shows and every figure draws
      plots/<section>/*.png the figures, one folder per section (overall, source-*, view-*)
      gallery/<frame>.png   sample frames with cuboids and bird's-eye views

The page works offline from the folder (relative links only). Steps are timed apart so the cost
of the statistics (target: 40,000 frames in under 20 s) is not confused with the optional image
check and gallery, which read files and grow with what is asked of them.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from jinja2 import Environment, FileSystemLoader, StrictUndefined
from markupsafe import Markup

from omnigen import __version__
from omnigen.dataset import Dataset
from omnigen.files import atomic_write_text
from omnigen.outputs import refuse_inputs
from omnigen.ownership import claim_output
from omnigen.priors import FAR_SIGMA
from omnigen.stats.compute import OCCLUSION_LEVEL_NAMES, compute_stats, derive
from omnigen.stats.gallery import GALLERY_MIN_SIDE, JOB, too_small, write_gallery
from omnigen.stats.health import check_health
from omnigen.stats.tracks import has_sequences, tracks_section
from omnigen.stats.plots import CAMERA_LABELS, FIGURES, figures_for, plot_section

TEMPLATES = Path(__file__).parent / "templates"


# ---------------------------------------------------------------------------------------------
# Number formatting: one rule, used by the page and by the test that checks the page against the JSON
# ---------------------------------------------------------------------------------------------


def format_number(v: Any) -> str | None:
    """Integers with thousands separators; other numbers to 3 significant digits; None for no value."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return None
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, int) or (isinstance(v, float) and v.is_integer() and abs(v) >= 1000):
        return f"{int(v):,}"
    if abs(v) >= 1000:
        return f"{v:,.0f}"
    return f"{v:.3g}"


def format_percent(v: Any) -> str | None:
    """A fraction as a percentage with one decimal."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return None
    return f"{100.0 * v:.1f}%"


def _num(v: Any) -> Markup:
    text = format_number(v)
    return Markup('<span class="na">&ndash;</span>') if text is None else Markup('<span class="num">%s</span>') % text


def _pct(v: Any) -> Markup:
    text = format_percent(v)
    return Markup('<span class="na">&ndash;</span>') if text is None else Markup('<span class="pct">%s</span>') % text


def environment(check: Callable[[Any], None] | None = None) -> Environment:
    """The page's jinja2 environment; `check`, when given, sees every number before it is shown
    (the test uses it to prove each one comes from stats.json)."""
    env = Environment(loader=FileSystemLoader(str(TEMPLATES)), autoescape=True, undefined=StrictUndefined)

    def num(v: Any) -> Markup:
        if check is not None:
            check(v)
        return _num(v)

    def pct(v: Any) -> Markup:
        if check is not None:
            check(v)
        return _pct(v)

    env.filters["num"] = num
    env.filters["pct"] = pct
    return env


# ---------------------------------------------------------------------------------------------
# The report
# ---------------------------------------------------------------------------------------------


@dataclass
class ReportResult:
    stats: dict[str, Any]
    out: Path
    figures: int
    timings: dict[str, float] = field(default_factory=dict)


def report_sections(stats: dict[str, Any]) -> list[dict[str, Any]]:
    """The page's sections in order (overall, each source, each view) and their figure files.

    A breakdown with a single group repeats the overall numbers; it is listed (so the page says
    so) but not drawn again.
    """
    out = [{"key": "overall", "label": "All frames", "data": stats["overall"], "same_as": None}]
    for part, prefix, label in (("by_source", "source", "Source"), ("by_view", "view", "View")):
        groups = stats[part]
        for name, sec in groups.items():
            out.append({"key": f"{prefix}-{name}", "label": f"{label}: {name}", "data": sec,
                        "same_as": "overall" if len(groups) == 1 else None})
    for s in out:
        names = [] if s["same_as"] else figures_for(s["data"])
        s["plots"] = {name: f"plots/{s['key']}/{name}.png" for name in names}
    return out


def render_page(stats: dict[str, Any], check: Callable[[Any], None] | None = None) -> str:
    """index.html from stats.json's content alone."""
    return environment(check).get_template("index.html.j2").render(
        stats=stats, sections=report_sections(stats), captions={k: v[0] for k, v in FIGURES.items()},
        camera_labels=CAMERA_LABELS, occlusion_levels=OCCLUSION_LEVEL_NAMES, version=__version__)


def _plot_job(args: tuple[dict[str, Any], dict[str, Any], str]) -> int:
    sec, stats, folder = args
    return len(plot_section(sec, stats, Path(folder)))


def _made_by_stats(folder: Path) -> bool:
    """A report from before the .omnigen-job marker: its stats.json and index.html are there."""
    return (folder / "stats.json").is_file() and (folder / "index.html").is_file()


def write_report(ds: Dataset, out: str | Path, gallery: int = 6, check_images: bool = True,
                 prior_sigma: float = FAR_SIGMA, seed: int = 0, jobs: int = 1,
                 show_progress: bool = True) -> ReportResult:
    """Compute, check, draw and write the whole report; returns the stats and each step's seconds."""
    out = Path(out)
    # The report deletes its own folders below: claimed first, so a folder it did not make (a
    # dataset, say, given as --out by mistake) is refused with nothing touched; so is a folder
    # inside the dataset, or one that holds it.
    refuse_inputs(out, [ds.root], JOB)
    claim_output(out, JOB, _made_by_stats)
    for sub in ("plots", "gallery"):  # the report's own folders: no figure of an older report may linger
        shutil.rmtree(out / sub, ignore_errors=True)
    timings: dict[str, float] = {}

    t = time.perf_counter()
    derived = derive(ds)
    stats = compute_stats(ds, derived)
    if has_sequences(ds):  # absent otherwise: older datasets' stats.json is unchanged
        stats["tracks"] = tracks_section(ds)
    health = check_health(ds, prior_sigma, check_images=False)
    timings["statistics"] = time.perf_counter() - t

    if check_images:
        t = time.perf_counter()
        from omnigen.stats.health import image_checks

        health["checks"] += image_checks(ds, limit=health["example_limit"], show_progress=show_progress)
        health["problems"] = sum(c["count"] for c in health["checks"])
        health["images_checked"] = True
        timings["image check"] = time.perf_counter() - t
    stats["health"] = health

    t = time.perf_counter()
    todo = [s for s in report_sections(stats) if s["plots"]]
    jobs_args = [(s["data"], stats, str(out / "plots" / s["key"])) for s in todo]
    if jobs > 1 and len(todo) > 1:
        with ProcessPoolExecutor(min(jobs, len(todo))) as pool:
            figures = sum(pool.map(_plot_job, jobs_args))
    else:
        figures = sum(_plot_job(a) for a in jobs_args)
    timings["figures"] = time.perf_counter() - t

    t = time.perf_counter()
    stats["gallery"] = write_gallery(ds, out, gallery, seed) if gallery > 0 else []
    stats["gallery_too_small"] = {"frames": int(too_small(ds).sum()), "min_side": GALLERY_MIN_SIDE}
    timings["gallery"] = time.perf_counter() - t

    t = time.perf_counter()
    # Insertion order, not sorted keys: the page follows the JSON's order (sources, classes, checks),
    # so rendering the page again from stats.json gives the same bytes.
    atomic_write_text(out / "stats.json", json.dumps(stats, separators=(",", ":"), allow_nan=False) + "\n")
    atomic_write_text(out / "index.html", render_page(stats))
    timings["page"] = time.perf_counter() - t
    return ReportResult(stats, out, figures, timings)
