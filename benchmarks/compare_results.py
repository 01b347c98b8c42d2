"""Two make validate runs side by side: the headline, each view and each class, from their results.json.

Why: a recipe change is judged by a whole make validate run (a 100-minute training on 2 cores), and
its effect lives in the rows: class-balanced sampling, for instance, should move the rare classes and
may cost cars. Reading two RESULTS.md files by eye invites copied numbers; this prints the rows of
both runs and their differences from the files the runs wrote (`docs/results.json`, or an earlier
run's from git: `git show COMMIT:docs/results.json > old.json`).

    .venv/bin/python benchmarks/compare_results.py OLD.json NEW.json [--labels OLD NEW]

Prints the headline (synthetic test split), the views and the classes (whole test split; mAP50:95,
AP50, recall at the best-F1 confidence) and, last,
`compare: mAP50:95 X -> Y (target T); classes better N, worse M, of K`.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old", type=Path, help="the earlier run's results.json")
    ap.add_argument("new", type=Path, help="the later run's results.json")
    ap.add_argument("--labels", nargs=2, default=("old", "new"), metavar=("OLD", "NEW"), help="column names")
    return ap.parse_args(argv)


def load(path: Path) -> dict[str, Any]:
    """A validate results.json, refused with the file and the field named when it is not one."""
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise SystemExit(f"compare_results: {path}: not a readable JSON file ({e})")
    for field in ("oks_map50_95", "by_view", "by_class"):
        if field not in data:
            raise SystemExit(f"compare_results: {path}: no field {field!r} (not a benchmarks/validate.py results.json)")
    return data


def fmt(x: Any, digits: int = 3) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def delta(a: Any, b: Any, digits: int = 3) -> str:
    if a is None or b is None or (isinstance(a, float) and math.isnan(a)) or (isinstance(b, float) and math.isnan(b)):
        return "-"
    d = b - a
    return f"{0.0:.{digits}f}" if abs(d) < 0.5 * 10 ** -digits else f"{d:+.{digits}f}"


CPU_TARGET = 0.10
"""Issue 25's synthetic-test OKS mAP50:95 for make validate at its CPU default (the design's 0.55
stands for a GPU run)."""

HEADLINE = (("oks_map50_95", "OKS mAP50:95", 3), ("ap_oks50", "AP50", 3), ("precision", "precision", 3),
            ("recall", "recall", 3), ("f1", "F1", 3), ("corner_error_px", "corner error px", 2),
            ("corner_error_rel", "corner error rel", 3))


def headline_rows(old: dict[str, Any], new: dict[str, Any]) -> list[tuple[str, str, str, str]]:
    rows = [(name, fmt(old.get(k), d), fmt(new.get(k), d), delta(old.get(k), new.get(k), d)) for k, name, d in HEADLINE]
    adh = (old["runs"][0]["synthetic_test"].get("ground_adherence_deg") if old.get("runs") else None,
           new["runs"][0]["synthetic_test"].get("ground_adherence_deg") if new.get("runs") else None)
    rows.append(("adherence (deg)", fmt(adh[0], 2), fmt(adh[1], 2), delta(*adh, 2)))
    base = (old.get("baseline", {}).get("corner_error_rel"), new.get("baseline", {}).get("corner_error_rel"))
    rows.append(("box template's corner error rel", fmt(base[0]), fmt(base[1]), delta(*base)))
    return rows


def group_rows(old: list[dict[str, Any]], new: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The groups of both runs in the later run's order (then any only the earlier one has)."""
    by_old = {g["group"]: g for g in old}
    by_new = {g["group"]: g for g in new}
    names = [g["group"] for g in new] + [g["group"] for g in old if g["group"] not in by_new]
    return [{"group": n, "old": by_old.get(n, {}), "new": by_new.get(n, {})} for n in names]


def table(title: str, labels: tuple[str, str], rows: list[dict[str, Any]]) -> list[str]:
    a, b = labels
    lines = [f"### {title}", "",
             f"| group | test objects ({a} / {b} where they differ) | mAP50:95 {a} | {b} | change | AP50 {a} | {b} | recall {a} | {b} |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        o, n = r["old"], r["new"]
        counts = {o.get("objects"), n.get("objects")} - {None}
        objects = "-" if not counts else str(counts.pop()) if len(counts) == 1 else f"{o['objects']} / {n['objects']}"
        lines.append(f"| {r['group'].split('=', 1)[-1]} | {objects} | "
                     f"{fmt(o.get('oks_map50_95'))} | {fmt(n.get('oks_map50_95'))} | "
                     f"{delta(o.get('oks_map50_95'), n.get('oks_map50_95'))} | {fmt(o.get('ap_oks50'))} | "
                     f"{fmt(n.get('ap_oks50'))} | {fmt(o.get('recall'))} | {fmt(n.get('recall'))} |")
    return lines + [""]


def compare(old: dict[str, Any], new: dict[str, Any], labels: tuple[str, str]) -> tuple[list[str], dict[str, Any]]:
    """The printed lines and a summary: the headline change and how many classes moved which way."""
    a, b = labels
    lines = ["### Synthetic test split", "", f"| metric | {a} | {b} | change |", "|---|---|---|---|"]
    lines += [f"| {' | '.join(r)} |" for r in headline_rows(old, new)] + [""]
    lines += table("By view (synthetic test split)", labels, group_rows(old["by_view"], new["by_view"]))
    classes = group_rows(old["by_class"], new["by_class"])
    lines += table("By class (whole test split)", labels, classes)
    moved = [(r["new"].get("oks_map50_95"), r["old"].get("oks_map50_95")) for r in classes]
    # as printed: a change that rounds to 0.000 is no change; a class without a score in one run is left out
    moved = [(round(n, 3), round(o, 3)) for n, o in moved
             if n is not None and o is not None and not (math.isnan(n) or math.isnan(o))]
    summary = {"old": old["oks_map50_95"], "new": new["oks_map50_95"], "target": CPU_TARGET,
               "better": sum(n > o for n, o in moved), "worse": sum(n < o for n, o in moved), "classes": len(moved)}
    return lines, summary


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    old, new = load(args.old), load(args.new)
    lines, s = compare(old, new, tuple(args.labels))
    print("\n".join(lines))
    print(f"compare: mAP50:95 {s['old']:.3f} -> {s['new']:.3f} (target {s['target']:.2f}); "
          f"classes better {s['better']}, worse {s['worse']}, of {s['classes']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
