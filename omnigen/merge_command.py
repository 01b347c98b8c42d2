"""Merge source datasets into UrbanOmniView with a held-out test split."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from omnigen.files import LINK_MODES
from omnigen.options import fraction, seed


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("sources", type=Path, nargs="*", help="source datasets (render and convert outputs)")
    p.add_argument("--out", type=Path, required=True, help="output dataset folder")
    p.add_argument("--taxonomy", default=None,
                   help="fine, coarse or a TOML file; recorded in the manifest (default: fine; with --update, the earlier merge's)")
    p.add_argument("--test-fraction", type=fraction(hi_open=True), default=None,
                   help="share of each source and view held out (default: 0.10; with --update, the earlier merge's)")
    p.add_argument("--seed", type=seed(), default=None,
                   help="seed of the test-split draw (default: 0; with --update, the earlier merge's)")
    p.add_argument("--split-file", type=Path, action="append", default=[],
                   help="a list of frame ids (or source ids such as KITTI's 000123); the file's stem names "
                        "the split; repeatable (e.g. train.txt and val.txt)")
    p.add_argument("--update", action="store_true", help="add sources to an existing merge, keeping its splits")
    p.add_argument("--link", choices=LINK_MODES, default="hardlink", help="how images are placed")


def run(args: argparse.Namespace) -> int:
    from omnigen.merge import DUPLICATES_SHOWN, merge
    from omnigen.progress import print_table
    from omnigen.taxonomy import load_taxonomy

    if not args.sources and not args.update:
        print("omnigen merge: give at least one source dataset", file=sys.stderr)
        return 2
    r = merge(args.sources, args.out, load_taxonomy(args.taxonomy) if args.taxonomy else None, args.test_fraction,
              args.seed, args.split_file, args.update, args.link)
    print_table(f"merge -> {args.out}", ["source", "frames", "test", "test share", "groups"],
                [[s.source, s.frames, s.test, f"{s.share:.2f}", s.groups] for s in r.shares])
    print_table("splits", ["split", "frames"], sorted(r.by_split.items()))
    test = r.by_split.get("test", 0)  # whole groups make the share reached differ from the one asked
    print(f"test split: {test} of {r.frames} frames ({test / max(r.frames, 1):.3f}; asked {r.test_fraction:g})")
    for line in unsplit_sources(r.shares, r.test_fraction):
        print(line)
    for path, n in sorted(r.unmatched_lines.items()):
        print(f"  {path}: {n} lines name no frame of these sources (left out)")
    if r.duplicate_frames:  # a frame in two sources is merged once: say which, never silently
        shown = r.duplicate_ids[:DUPLICATES_SHOWN]
        more = f" and {r.duplicate_frames - len(shown)} more" if r.duplicate_frames > len(shown) else ""
        print(f"duplicates: {r.duplicate_frames} frames are in more than one source with identical records and "
              f"pixels, kept once: {', '.join(shown)}{more}")
    links = ", ".join(f"{k} {v}" for k, v in sorted(r.link_modes.items())) or "-"
    print_table("summary", ["frames", "objects", "unique images", "duplicate frames", "images placed", "seconds"],
                [[r.frames, r.objects, r.unique_images, r.duplicate_frames, links, round(r.seconds, 2)]])
    return 0


def unsplit_sources(shares, fraction: float) -> list[str]:
    """A line for each source the test split could not take frames from, and what to do: a
    source of one group (one rendered city, one DAIR-V2X sequence) cannot be split without the
    same scene sitting on both sides, so all of it trains and nothing of it is evaluated."""
    if fraction <= 0:
        return []
    return [f"{s.source}: no test frames: its {s.frames} frames are one group (one rendered city or one recorded "
            "sequence), which a split keeps whole; render another city (another --seed) or pass --split-file "
            "to hold out frames of it" for s in shares if s.test == 0 and s.groups < 2]
