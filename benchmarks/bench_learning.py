"""The yardstick for recipe changes: train a fixed number of steps from a fixed seed, score the
synthetic test split against the box-template baseline.

    .venv/bin/python benchmarks/bench_learning.py runs/validate/uov --steps 2000
    .venv/bin/python benchmarks/bench_learning.py runs/validate/uov --steps 400 --kpt-mode box --kpt-l1 2

Why a fixed number of steps and not minutes: on a shared 2-core machine the time a step takes
varies with what else runs, the steps do not, so two recipes trained for the same steps compare
whatever the machine did meanwhile (the seconds are printed, not compared).

What it prints, for the model (its EMA weights after the last step) and for the box-template
baseline (each predicted box's corners placed by its class's and view's mean layout from the
training split, detector/box_template.py): OKS mAP50:95, AP50, ground-plane adherence, and the
median corner error of the box-matched objects in pixels and relative to sqrt(box area)
(detector/corner_errors.py), on the synthetic test frames and per view. A recipe whose
`corner_error_rel` is not below the baseline's has corners worth no more than the 2D box.
OKS mAP of a few hundred CPU steps sits near 0 and moves in noise; the corner errors move from
the first hundred steps on, which is why they are the figure to compare at small budgets.

Last line: `learning: mAP50:95 X (baseline Y), corner error rel A (baseline B)`.
`--out DIR/NAME.json` keeps the numbers; docs/detector-training.md tables what each recipe printed.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

RECIPE = {"imgsz": 640, "crop": 320, "batch": 16, "lr0": 2e-3, "kpt_sigma_end": 0.25, "amp": "bf16"}
"""make validate's CPU recipe (benchmarks/validate.py), the point every change is compared from."""

FIELDS = ("oks_map50_95", "ap_oks50", "ground_adherence_deg", "corner_error_px", "corner_error_rel", "corner_spread",
          "layout_error_rel",
          "corner_objects")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="a merged dataset with train and test splits (make validate's uov)")
    ap.add_argument("--steps", type=int, default=2000, help="optimiser steps (rounded up to whole epochs)")
    ap.add_argument("--work", type=Path, default=Path("runs/learning"), help="where the run folder goes")
    ap.add_argument("--name", default=None, help="run folder name (default: from the recipe's arguments)")
    ap.add_argument("--out", type=Path, default=None, help="write the numbers as JSON here")
    ap.add_argument("--imgsz", type=int, default=RECIPE["imgsz"])
    ap.add_argument("--crop", type=int, default=RECIPE["crop"], help="0: whole images")
    ap.add_argument("--crop-focus", type=float, default=0.0, help="with --crop: share of the windows centred class-balanced (train --crop-focus)")
    ap.add_argument("--repeat-thresh", type=float, default=0.0, help="repeat-factor sampling threshold (train --repeat-thresh); 0: off")
    ap.add_argument("--batch", type=int, default=RECIPE["batch"])
    ap.add_argument("--lr0", type=float, default=RECIPE["lr0"])
    ap.add_argument("--kpt-sigma-end", type=float, default=RECIPE["kpt_sigma_end"])
    ap.add_argument("--kpt-mode", default="anchor", choices=["anchor", "box"])
    ap.add_argument("--kpt-l1", type=float, default=0.0)
    ap.add_argument("--kpt-turn", action="store_true", help="corners up to the 180-degree turn plus a turn class")
    ap.add_argument("--kpt-hidden", type=int, default=None, help="keypoint-branch width (train --kpt-hidden)")
    ap.add_argument("--kpt-heading", action="store_true", help="corners up to the turn, the front from a regressed heading")
    ap.add_argument("--heading-gain", type=float, default=1.0, help="with --kpt-heading: the heading term's gain")
    ap.add_argument("--heading-crop", type=int, default=0, help="crop side of the second stage that places corners and reads the front (train --heading-crop); 0: none")
    ap.add_argument("--kpt-labelled", type=float, default=0.0, help="with --kpt-turn: the labelled-order OKS gain")
    ap.add_argument("--kpt-turn-start", type=float, default=0.0,
                    help="with --kpt-turn: fraction of the run compared as labelled only (train --kpt-turn-start)")
    ap.add_argument("--amp", default=RECIPE["amp"], choices=["auto", "bf16", "fp16", "off"])
    ap.add_argument("--model", default="n")
    ap.add_argument("--width", type=float, default=None, help="override the scale's width (tiny test models)")
    ap.add_argument("--depth", type=float, default=None)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--single-label", action="store_true",
                    help="score one class an anchor (as `omnigen predict` gives and as rows before 2026-11-27 were scored); default: every class above the floor, as omnigen eval")
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
    from omnigen.detector.checkpoint import load_checkpoint

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


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from benchmarks.validate import fmt
    from omnigen.detector.box_template import evaluate_with_baseline
    from omnigen.detector.corner_order import corner_order_counts
    from omnigen.detector.loss import PARTS
    from omnigen.detector.predict import predict_dataset
    from omnigen.detector.train import TrainConfig, train
    from omnigen.dataset import Dataset
    from omnigen.splits import read_split

    frames = len(read_split(args.dataset, "train"))
    if args.repeat_thresh:  # an epoch draws more frames: count them as train does, so --steps stays the steps trained
        from omnigen.detector.balance import epoch_frames
        from omnigen.detector.data import KeypointDataset, split_frames
        from omnigen.detector.train import frame_repeats
        from omnigen.taxonomy import load_taxonomy

        taxonomy = load_taxonomy(TrainConfig.taxonomy)  # the taxonomy the runs below train with
        split = KeypointDataset(args.dataset, taxonomy, args.imgsz, split_frames(str(args.dataset), "train"))
        frames = epoch_frames(frame_repeats(TrainConfig(dataset=str(args.dataset), out="-", repeat_thresh=args.repeat_thresh),
                                            split))
    per_epoch = math.ceil(frames / args.batch)
    epochs = max(1, math.ceil(args.steps / per_epoch))
    name = args.name or (f"{args.model}-{args.kpt_mode}{'-turn' if args.kpt_turn else ''}{'-heading' if args.kpt_heading else ''}{f'-hg{args.heading_gain:g}' if args.heading_gain != 1.0 else ''}{f'-h{args.kpt_hidden}' if args.kpt_hidden else ''}{f'-crop{args.heading_crop}' if args.heading_crop else ''}"
                         f"{f'-lab{args.kpt_labelled:g}' if args.kpt_labelled else ''}"
                         f"{f'-ts{args.kpt_turn_start:g}' if args.kpt_turn_start else ''}-l1{args.kpt_l1:g}-s{args.steps}"
                         f"-c{args.crop}{f'-f{args.crop_focus:g}' if args.crop_focus else ''}{f'-r{args.repeat_thresh:g}' if args.repeat_thresh else ''}"
                         f"-lr{args.lr0:g}-seed{args.seed}")
    run = args.work / name
    cfg = TrainConfig(dataset=str(args.dataset), out=str(run), model=args.model, width=args.width, depth=args.depth,
                      imgsz=args.imgsz, crop=args.crop or None, crop_focus=args.crop_focus,
                      repeat_thresh=args.repeat_thresh, epochs=epochs, batch=args.batch, lr0=args.lr0,
                      kpt_sigma_end=args.kpt_sigma_end, kpt_mode=args.kpt_mode, kpt_l1=args.kpt_l1,
                      kpt_turn=args.kpt_turn, kpt_hidden=args.kpt_hidden,
                      kpt_labelled=args.kpt_labelled, kpt_turn_start=args.kpt_turn_start, kpt_heading=args.kpt_heading, heading_crop=args.heading_crop, heading_gain=args.heading_gain, amp=args.amp, workers=args.workers, seed=args.seed, device=args.device,
                      val_every=0)  # no validation while training: the test split is scored below, once
    t0 = time.perf_counter()
    last = finished(run, cfg, epochs)
    if last is None:
        last = train(cfg, resume=False)
    else:
        print(f"{run}: trained before with these arguments; scoring its last.pt")
    train_s = time.perf_counter() - t0 if last.get("time") is None else float(last["time"])
    # the network's own corners (vertical="off"), as the rows written down before the snap
    preds = predict_dataset(run / "last.pt", args.dataset, split="test", imgsz=args.imgsz, batch=8, device=args.device,
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
