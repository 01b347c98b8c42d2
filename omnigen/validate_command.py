"""Check a dataset: its manifest, each record's schema and plausible values, files present, unique ids."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from omnigen.options import integer


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path)
    p.add_argument("--max-problems", type=integer(0), default=50, help="how many problems to list (all are counted)")


def run(args: argparse.Namespace) -> int:
    from omnigen.checks import check_dataset
    from omnigen.progress import print_table

    start = time.perf_counter()
    n, problems = check_dataset(args.dataset)
    for p in problems[: args.max_problems]:
        print(f"  {p}")
    if len(problems) > args.max_problems:
        print(f"  ... and {len(problems) - args.max_problems} more")
    print_table(f"validate {args.dataset}", ["frames", "problems", "seconds"],
                [[n, len(problems), round(time.perf_counter() - start, 2)]])
    if problems:
        print(f"{args.dataset}: INVALID ({len(problems)} problems)")
        return 1
    print(f"{args.dataset}: valid")
    return 0
