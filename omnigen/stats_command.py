"""Write a dataset's statistics report (index.html, stats.json, PNG figures)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from omnigen.options import integer, number, seed


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path)
    p.add_argument("--out", type=Path, required=True,
                   help="report folder (created; a rerun replaces its files; a folder of other files is refused)")
    p.add_argument("--gallery", type=integer(0), default=6, help="sample frames drawn with cuboids and BEV (0: none)")
    p.add_argument("--no-check-images", dest="check_images", action="store_false",
                   help="do not open every image's header (the one step that reads a file per frame)")
    p.add_argument("--prior-sigma", type=number(0, lo_open=True), default=None,
                   help="flag dimensions this many spreads from their class prior (default: omnigen.priors.FAR_SIGMA)")
    p.add_argument("--seed", type=seed(), default=0, help="seed of the gallery's pick")
    p.add_argument("--jobs", type=integer(0), default=0, help="processes drawing figures (0: up to 4, one per core)")


def run(args: argparse.Namespace) -> int:
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
