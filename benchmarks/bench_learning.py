"""The yardstick for recipe changes: train a fixed number of steps from a fixed seed, score the
synthetic test split against the box-template baseline.

    .venv/bin/python benchmarks/bench_learning.py runs/validate/uov --steps 2000
    .venv/bin/python benchmarks/bench_learning.py runs/validate/uov loss.kpt_l1=1 crop_stage.steps=0 --steps 400

What is trained is `omnigen train`'s recipe (detector/recipe.py, make validate's), its crop phase
included; a change to compare is given as its KEY=VALUE keys right after the dataset (or a recipe
file, --recipe), as `omnigen train` takes them.

Why a fixed number of steps and not minutes: on a shared 2-core machine the time a step takes
varies with what else runs, the steps do not, so two recipes trained for the same steps compare
whatever the machine did meanwhile (the seconds are printed, not compared).

What it prints, for the model (its EMA weights after the last step) and for the box-template
baseline (each predicted box's corners placed by its class's and view's mean layout from the
training split, detector/evaluation/box_template.py): OKS mAP50:95, AP50, ground-plane adherence, and the
median corner error of the box-matched objects in pixels and relative to sqrt(box area)
(detector/evaluation/corner_errors.py), on the synthetic test frames and per view. A recipe whose
`corner_error_rel` is not below the baseline's has corners worth no more than the 2D box.
OKS mAP of a few hundred CPU steps sits near 0 and moves in noise; the corner errors move from
the first hundred steps on, which is why they are the figure to compare at small budgets.

Last line: `learning: mAP50:95 X (baseline Y), corner error rel A (baseline B)`.
`--out DIR/NAME.json` keeps the numbers; docs/detector-training.md tables what each recipe printed.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.detector.recipe import RUN  # noqa: E402

FIELDS = ("oks_map50_95", "ap_oks50", "ground_adherence_deg", "corner_error_px", "corner_error_rel", "corner_spread",
          "layout_error_rel",
          "corner_objects")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="a merged dataset with train and test splits (make validate's uov)")
    ap.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="recipe keys to change (omnigen train's)")
    ap.add_argument("--recipe", type=Path, default=None, help="start from this recipe file (omnigen train --recipe)")
    ap.add_argument("--steps", type=int, default=2000, help="optimiser steps (rounded up to whole epochs)")
    ap.add_argument("--work", type=Path, default=Path("runs/learning"), help="where the run folder goes")
    ap.add_argument("--name", default=None, help="run folder name (default: from the keys changed)")
    ap.add_argument("--out", type=Path, default=None, help="write the numbers as JSON here")
    ap.add_argument("--amp", default="bf16", choices=["auto", "bf16", "fp16", "off"],
                    help="precision of the steps (bf16: make validate's on a CPU that runs it natively)")
    ap.add_argument("--width", type=float, default=None, help="override the scale's width (tiny test models)")
    ap.add_argument("--depth", type=float, default=None)
    ap.add_argument("--workers", type=int, default=RUN.workers, help="loader processes (default: train's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--single-label", action="store_true",
                    help="score one class an anchor (as `omnigen predict` gives, and as the earliest rows were scored); "
                         "default: every class above the floor, as omnigen eval")
    return ap.parse_args(argv)


def rows_of(report: Any, by_class: bool = False) -> dict[str, dict[str, float]]:
    """The synthetic row (else overall) and the per-view rows of an EvalReport, FIELDS only; with
    `by_class` also each class's row, keyed as the report names it ('class=car')."""
    rows = {r.group: r for r in report.rows}
    main = rows.get("source=synthetic") or rows["overall"]
    out = {"synthetic" if main.group == "source=synthetic" else "overall": main}
    out.update({g.split("=", 1)[1]: r for g, r in rows.items() if g.startswith("view=")})
    if by_class:
        out.update({g: r for g, r in rows.items() if g.startswith("class=")})
    def value(v: float) -> float | None:  # JSON has no NaN: a figure nothing was matched for is null
        return None if isinstance(v, float) and math.isnan(v) else v

    return {k: {f: value(getattr(r, f)) for f in FIELDS} for k, r in out.items()}


IGNORED = ("out", "device", "workers", "cache", "val_every", "val_split")
"""Training arguments that do not change the weights a run ends with (where it runs, what it validates on)."""


def finished(run: Path, cfg: Any, epochs: int) -> dict[str, Any] | None:
    """The last history row of a run folder that already holds this recipe trained to its end
    (the same training arguments, its last epoch written), so a rerun only scores it; None when
    the folder has no checkpoint. A checkpoint of other arguments, or one cut off before its end,
    is refused rather than trained over: it may be the only copy of an hour's run."""
    from omnigen.detector.model.checkpoint import load_checkpoint

    path = run / "last.pt"
    if not path.exists():
        return None
    state = load_checkpoint(path)
    saved, wanted = dict(state.get("train_config", {})), asdict(cfg)
    for key in ("dataset",):  # the same folder however it was spelled
        saved[key], wanted[key] = (str(Path(d).resolve()) if d else d for d in (saved.get(key), wanted[key]))
    differ = sorted(k for k, v in wanted.items()
                    if k in saved and saved[k] != v and k not in IGNORED)
    if differ:
        raise SystemExit(f"bench_learning: {path} was trained with other arguments ({', '.join(differ)}); "
                         "give another --name or --work, or delete the folder")
    if int(state["epoch"]) + 1 != epochs or not state.get("history"):
        raise SystemExit(f"bench_learning: {path} stopped at epoch {int(state['epoch']) + 1} of {epochs}; "
                         "delete the folder to train it again")
    return state["history"][-1]


def run_name(args: argparse.Namespace, recipe: Any) -> str:
    """A run folder's name from what sets it apart: the recipe file, the keys changed, the steps, the seed."""
    import re

    keys = "-".join(re.sub(r"[^\w.=,-]", "_", k) for k in args.overrides)
    base = f"{Path(args.recipe).stem}-" if args.recipe else ""
    return f"{recipe.model.scale}-{base}{keys or 'recipe'}-s{args.steps}-seed{args.seed}"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from benchmarks.common import fmt
    from omnigen.detector.evaluation.box_template import evaluate_with_baseline
    from omnigen.detector.evaluation.corner_order import corner_order_counts
    from omnigen.detector.training.loss import PARTS
    from omnigen.detector.prediction.predict import predict_dataset
    from omnigen.detector.training.train import TrainConfig, train
    from omnigen.dataset import Dataset
    from omnigen.splits import read_split

    from omnigen.detector.recipe import resolve, train_fields

    recipe = resolve(args.recipe, args.overrides)
    fields = train_fields(recipe)
    frames = len(read_split(args.dataset, "train"))
    if fields["repeat_thresh"]:  # an epoch draws more frames: count them as train does, so --steps stays the steps trained
        from omnigen.detector.data.balance import epoch_frames
        from omnigen.detector.data.samples import KeypointDataset, split_frames
        from omnigen.detector.training.train import frame_repeats
        from omnigen.taxonomy import load_taxonomy

        split = KeypointDataset(args.dataset, load_taxonomy(fields["taxonomy"]), fields["imgsz"],
                                split_frames(str(args.dataset), "train"))
        frames = epoch_frames(frame_repeats(TrainConfig(dataset=str(args.dataset), out="-", **fields), split))
    per_epoch = math.ceil(frames / fields["batch"])
    epochs = max(1, math.ceil(args.steps / per_epoch))
    name = args.name or run_name(args, recipe)
    run = args.work / name
    cfg = TrainConfig(dataset=str(args.dataset), out=str(run), **fields, width=args.width, depth=args.depth,
                      epochs=epochs, amp=args.amp, workers=args.workers, seed=args.seed, device=args.device,
                      val_every=0)  # no validation while training: the test split is scored below, once
    t0 = time.perf_counter()
    last = finished(run, cfg, epochs)
    if last is None:
        last = train(cfg, resume=False)
    else:
        print(f"{run}: trained before with these arguments; scoring its last.pt")
    train_s = time.perf_counter() - t0 if last.get("time") is None else float(last["time"])
    # the network's own corners (vertical="off"), as the rows written down before the snap
    preds = predict_dataset(run / "last.pt", args.dataset, split="test", imgsz=cfg.imgsz, batch=8, device=args.device,
                            multi_label=not args.single_label, vertical="off")
    ds = Dataset.open(args.dataset, show_progress=False)
    report, baseline = evaluate_with_baseline(ds, preds, split="test", taxonomy=cfg.taxonomy)
    model_rows, base_rows = rows_of(report), rows_of(baseline)
    orders = corner_order_counts(ds, preds, split="test")
    main_key = next(iter(model_rows))
    result = {"dataset": str(args.dataset), "name": name, "steps": epochs * per_epoch, "epochs": epochs,
              "train_seconds": round(train_s, 1), "config": asdict(cfg), "multi_label": not args.single_label,
              "final_losses": {k: last.get(k) for k in PARTS},
              "model": model_rows, "baseline": base_rows,
              "corner_order": {"matched": orders.matched,
                               **{k: orders.fraction(k) if orders.matched else None for k in orders.best}}}

    print(f"\n{name}: {result['steps']} steps ({epochs} epochs of {per_epoch}), {train_s:.0f} s of training")
    print("| rows | model mAP50:95 | AP50 | adherence (deg) | corner error px | rel | layout rel | spread | "
          "baseline mAP50:95 | AP50 | px | rel | layout rel |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for key, m in model_rows.items():
        b = base_rows[key]
        print(f"| {key} | {fmt(m['oks_map50_95'])} | {fmt(m['ap_oks50'])} | {fmt(m['ground_adherence_deg'], 2)} | "
              f"{fmt(m['corner_error_px'], 2)} | {fmt(m['corner_error_rel'])} | {fmt(m.get('layout_error_rel'))} | "
              f"{fmt(m['corner_spread'], 2)} | {fmt(b['oks_map50_95'])} | "
              f"{fmt(b['ap_oks50'])} | {fmt(b['corner_error_px'], 2)} | {fmt(b['corner_error_rel'])} | "
              f"{fmt(b.get('layout_error_rel'))} |")
    # a heading the model cannot tell shows as objects whose corners fit best turned 180 degrees
    print(f"box-matched objects ({orders.matched}): as labelled {fmt(orders.fraction('as labelled'), 2)}, "
          f"turned 180 {fmt(orders.fraction('turned 180'), 2)}")
    if args.out:
        from omnigen.files import atomic_write_json

        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(args.out, result, indent=2)
    m, b = model_rows[main_key], base_rows[main_key]
    print(f"learning: mAP50:95 {fmt(m['oks_map50_95'])} (baseline {fmt(b['oks_map50_95'])}), "
          f"corner error rel {fmt(m['corner_error_rel'])} (baseline {fmt(b['corner_error_rel'])})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
