"""End-to-end validation: render, merge, train the recipe (nano+P2 and its crop stage), evaluate, BEV; writes docs/RESULTS.md and docs/results.json.

    make validate                                   # the default below, sized for a 2-core machine
    .venv/bin/python benchmarks/validate.py --kitti ../shared/realdata/kitti --ablations no-p2
    .venv/bin/python benchmarks/validate.py --frames 2000 --set data.window=0 --epochs 100 --scales n s m --device cuda

Every stage is a command of the toolkit, run in this process and recorded with its wall time; a
stage whose output already exists is skipped, so an interrupted run resumes, and a training cut off
midway (a kill, a time-boxed job) goes on from its last checkpoint, the time of the epochs it kept
counted (`--fresh` starts over; a working folder rendered with other data arguments is refused
rather than silently reused).

What is trained is `omnigen train`'s own recipe (detector/recipe.py): this script passes the data
and the budget, never a recipe value (`--recipe FILE` and `--set KEY=VALUE` change it, as they do
train's). Its defaults fit a 2-core CPU: 600 raster frames at 640 x 640, training on random
320 x 320 windows of the 640-pixel input (data.window: a step costs what a 320-pixel input costs
while every object keeps the scale it has when the model predicts on the whole image), then the
crop stage (each detection's corners, front and class from its own crop) trained again apart on
clean crops for 7000 steps, the run's second phase (RESULTS.md gives its seconds). Training
is time-boxed (`--minutes 125`, train --time): the detector's schedule is planned over the epochs
that fit in 100 minutes, at most `--epochs`, and the crop phase has the rest; rendering before it
and predicting, evaluating and the BEV head after it add minutes (RESULTS.md lists each stage's time). On a CPU that runs
bfloat16 natively the steps run in bf16 (`--amp`, about 0.65 of a float32 step by
benchmarks/bench_train_speed.py; the crop phase's too). The images are decoded once and kept in memory (train --cache,
565 MiB here; `--no-cache` reads them every epoch): on 2 cores train loads in the step's own process,
where one process decoded 70.6 training images a second from disk and 461.8 from memory
(benchmarks/bench_train_speed.py throughput --recipe). It trains the same weights, so runs done
without it are kept. Scaling up: more frames per rig (`--frames`), whole images
(`--set data.window=0`), more epochs, Cycles instead of the raster preview (`--backend cycles`),
the ablations of the design's Table 8 (`--ablations`: without synthetic data, without P2, a 1.5x
larger input) and the other scales (`--scales n s m`) where a GPU makes them affordable; see
docs/RESULTS.md for what ran here.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import hashlib
import json
import shutil
import statistics
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (SCENE_MIX, Runner, check_data_arguments, floor_rows, fmt, kept_sections,  # noqa: E402
                               machine, render_jobs, run_renders, stale, synthetic_row, train_stage)
from omnigen.detector.evaluation.oks_eval import SIZE_BINS  # noqa: E402
from omnigen.detector.recipe import RECIPE, RUN, Recipe, resolve, train_fields  # noqa: E402
from omnigen.files import atomic_write_json, atomic_write_text, file_digest  # noqa: E402

if TYPE_CHECKING:
    from omnigen.dataset import Dataset

TARGET_MAP = 0.55  # the design's nano reaches 0.559 on its mixed data
TARGET_ADHERENCE = 3.57  # degrees, the design's synthetic figure
FLOOR_NOISE_PX = [0.0, 1.0, 2.0]
BASELINE_FIELDS = ("oks_map50_95", "ap_oks50", "ground_adherence_deg", "corner_error_px", "corner_error_rel")  # corner noise of the "what the truth's own corners score" rows


def stale_or_missing(marker: Path, stamp: str) -> bool:
    """A stage's output made before its marker existed (an older validate) or with other arguments."""
    return not marker.exists() or stale(marker, stamp)


def predict_stage(run: Runner, out: Path, uov: Path, multi_label: bool,
                  predict: Callable[[bool], list[dict[str, Any]]], weights: Path | None = None,
                  vertical: str = RECIPE.predict.vertical) -> Path:
    """OUT/test-predictions.json, made by `predict(multi_label)` unless it was made the same way before.

    OUT/predicted holds how (the checkpoint, OUT/last.pt unless `weights` names another, and a digest
    of its bytes, the split,
    the labels an anchor, the score floor, the detections kept an image, the crop stage's
    refinements, whether vertical edges are snapped: PredictOptions.vertical). Predictions made
    otherwise, or by a validate older than the marker, are made again. Whenever they are made, their
    old evaluation (OUT/eval.json) goes: a changed evaluation protocol, or predictions deleted to
    redo them, must not leave old figures standing.
    """
    from omnigen.detector.model.crop_stage import MAX_REFINE
    from omnigen.detector.prediction.predict import EVAL_CONF, EVAL_MAX_DET

    preds, predicted = out / "test-predictions.json", out / "predicted"
    weights = weights or out / "last.pt"
    # the checkpoint's bytes too: train-crop writes another stage into the same crop.pt
    digest = f", weights_sha256={file_digest(weights)}" if weights.exists() else ""
    call = (f"predict_dataset({weights}, {uov}, split='test', multi_label={multi_label}, "
            f"conf={EVAL_CONF}, max_det={EVAL_MAX_DET}, max_refine={MAX_REFINE}, vertical={vertical!r}{digest})")
    if preds.exists() and stale_or_missing(predicted, call):
        print(f"[stale] {preds} was predicted otherwise: predicting and evaluating again", flush=True)
        preds.unlink()
        run.drop(f"predict_dataset({out}/")
    if not preds.exists():
        (out / "eval.json").unlink(missing_ok=True)  # an evaluation of other predictions
        t0 = time.perf_counter()
        atomic_write_text(preds, json.dumps(predict(multi_label)))
        atomic_write_text(predicted, call + "\n")
        run.record(call, time.perf_counter() - t0)
    return preds


def default_amp(device: str | None) -> str:
    """bf16 when training runs on a CPU with native bf16 (the 2-core default), else train's auto."""
    import torch

    from omnigen.detector.training.train import fast_bf16

    on_cpu = device == "cpu" if device else not torch.cuda.is_available()
    return "bf16" if on_cpu and fast_bf16(torch.device("cpu")) else "auto"


DATA_ARGUMENTS = ("frames", "cities", "size", "backend", "seed", "scene", "kitti", "dair")
"""The arguments that shape the data: a working folder made with others is refused (check_data_arguments)."""


def render_all(run: Runner, work: Path, args: argparse.Namespace) -> list[Path]:
    """Each rig renders --cities cities (one seed each: frames of one city form one split group, so
    several are needed for a group-aware test split), --jobs renders at a time."""
    jobs = render_jobs(work, args)
    run_renders(run, [argv for argv, out in jobs if not (out / "manifest.json").exists()], args.jobs)
    return [out for _, out in jobs]


def time_box(args: argparse.Namespace) -> list[str]:
    """`omnigen train --time MINUTES` from --minutes (none for 0): the trainer plans the epochs that
    fit, so the 2-hour figure of the default run is a budget kept, not a projection."""
    return ["--time", str(args.minutes)] if args.minutes else []


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("runs/validate"), help="working folder (resumable)")
    ap.add_argument("--kitti", type=Path, help="a KITTI tree to convert and merge (real data)")
    ap.add_argument("--dair", type=Path, help="a DAIR-V2X tree to convert and merge (real data)")
    ap.add_argument("--frames", type=int, default=200, help="frames per rig")
    ap.add_argument("--cities", type=int, default=5, help="cities (seeds) per rig: the split groups")
    ap.add_argument("--scene", default=SCENE_MIX,
                    help="city preset or mix of presets (omnigen render --scene): each city seed draws one")
    ap.add_argument("--size", type=int, default=640, help="rendered image width and height")
    ap.add_argument("--backend", default="raster", choices=["raster", "cycles"])
    ap.add_argument("--jobs", type=int, default=2, help="concurrent render processes")
    ap.add_argument("--epochs", type=int, default=RUN.epochs, help="epochs at most (--minutes may plan fewer)")
    ap.add_argument("--minutes", type=float, default=125.0,
                    help="training's wall-clock budget per model, both phases (train --time): the detector's schedule "
                         "is fitted to the epochs that fit in its 100 minutes, the crop stage's to the rest; 0: none")
    ap.add_argument("--workers", type=int, default=RUN.workers,
                    help="loader processes (default: train's, none on a CPU of 2 cores or fewer)")
    ap.add_argument("--cache", action=argparse.BooleanOptionalAction, default=True,
                    help="train with the images decoded once, in memory (train --cache)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--recipe", type=Path, default=None,
                    help="train this recipe file instead of the validated one (omnigen train --recipe)")
    ap.add_argument("--set", nargs="+", action="extend", default=[], metavar="KEY=VALUE",
                    help="recipe keys to change for every run (omnigen train KEY=VALUE; data.window=0: whole images)")
    ap.add_argument("--amp", default=None, choices=["auto", "bf16", "fp16", "off"],
                    help="mixed precision of training (default: bf16 when training on a CPU that runs it "
                         "natively, else auto)")
    ap.add_argument("--val-every", type=int, default=50,
                    help="validate every N epochs (and at the end): the curve in results.csv; the test split is "
                         "evaluated with the last weights, never the best-validated ones; each validation refines "
                         "the test frames' detections with the crop stage, so fewer validations leave more budget")
    ap.add_argument("--scales", nargs="+", default=["n"], help="model scales to train with P2 (n first)")
    ap.add_argument("--ablations", nargs="*", default=[], choices=["no-p2", "hires", "no-synthetic"],
                    help="also train: without P2, at 1.5x the input size (same crop), on the real sources alone")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--results", type=Path, default=Path("docs"), help="where RESULTS.md and results.json go")
    ap.add_argument("--fresh", action="store_true", help="delete the working folder first")
    ap.add_argument("--data-only", action="store_true",
                    help="stop once the dataset (WORK/uov) is merged: the data bench_learning.py compares recipes on")
    return ap


def run_recipe(args: argparse.Namespace, keys: list[str] = ()) -> Recipe:
    """The recipe a run trains: --recipe's (else the validated one) with --set's keys and the run's
    own (`keys`: an ablation's), as `omnigen train` resolves them."""
    return resolve(args.recipe, [*args.set, *keys])


def check_recipe(ap: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse, before any data stage, a recipe `omnigen train` would refuse at training: an unknown
    key, a value of the wrong type or range, sampling settings train's own check refuses."""
    from omnigen.detector.training.train import TrainConfig, check_sampling, check_sizes

    try:
        fields = train_fields(run_recipe(args))
        cfg = TrainConfig(dataset=str(args.work), out=str(args.work), **fields)
        check_sizes(cfg)
        check_sampling(cfg)
    except ValueError as e:
        ap.error(f"the recipe: {e}")


def predict_test_split(run: Runner, out: Path, uov: Path, recipe: Recipe, device: str | None) -> Path:
    """OUT/test-predictions.json of a run's last.pt (predict_stage), predicted as its recipe says: at
    its input size and batch, vertical edges snapped or not by predict.vertical (`--set
    predict.vertical=off`: the corners as the network placed them).

    last.pt, not best.pt: without a val split, train validates on the test split, and choosing the
    checkpoint by its test score would flatter the number reported here. It holds the crop stage of
    the run's second phase (trained again apart on clean crops)."""
    from omnigen.detector.prediction.predict import EVAL_MULTI_LABEL, predict_dataset

    weights, vertical = out / "last.pt", recipe.predict.vertical
    return predict_stage(run, out, uov, EVAL_MULTI_LABEL, lambda multi_label: predict_dataset(
        weights, uov, split="test", imgsz=recipe.model.imgsz, batch=recipe.optim.batch, device=device,
        multi_label=multi_label, vertical=vertical), weights=weights, vertical=vertical)


def train_command(args: argparse.Namespace, dataset: Path, out: Path, keys: list[str] = (),
                  options: list[str] = ()) -> list[str]:
    """`omnigen train` of one run: the dataset, the recipe (--recipe, --set and the run's `keys`),
    and validate's budget and machine settings; nothing of the recipe's own values, which train
    takes from detector/recipe.py."""
    recipe = ["--recipe", str(args.recipe)] if args.recipe else []
    workers = ["--workers", str(args.workers)] if args.workers is not None else []  # else train's own choice
    return ["train", str(dataset), *args.set, *keys, "--out", str(out), *recipe, "--epochs", str(args.epochs),
            *workers, "--seed", str(args.seed), "--val-every", str(args.val_every),
            "--amp", args.amp, *time_box(args), *(["--device", args.device] if args.device else []),
            *(["--cache"] if args.cache else []), *options]


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    check_recipe(ap, args)
    args.amp = args.amp or default_amp(args.device)  # resolved, so RESULTS.md's command line says which

    work = args.work
    if args.fresh and work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    check_data_arguments(work, args, DATA_ARGUMENTS)
    run = Runner(work, who="validate")
    sources = render_all(run, work, args)
    real = []
    if args.kitti:
        run(["convert", "kitti", str(args.kitti), "--out", str(work / "kitti")], work / "kitti" / "manifest.json")
        real.append(work / "kitti")
    if args.dair:
        run(["convert", "dair", str(args.dair), "--out", str(work / "dair")], work / "dair" / "manifest.json")
        real.append(work / "dair")
    uov = work / "uov"
    run(["merge", *map(str, sources + real), "--out", str(uov), "--test-fraction", "0.2", "--seed", str(args.seed)],
        uov / "manifest.json")
    if args.data_only:
        print(f"validate: the dataset is {uov} (--data-only: no training)")
        return 0

    from omnigen.detector.evaluation.corner_order import corner_order_counts
    from omnigen.dataset import Dataset

    uov_ds = Dataset.open(uov, show_progress=False)  # read once: the heading table and the object sizes
    runs: list[dict[str, Any]] = []

    def train_eval(name: str, keys: list[str], dataset: Path = uov, options: list[str] = ()) -> dict[str, Any]:
        out = work / "runs" / name
        t = train_stage(run, train_command(args, dataset, out, keys, options), out)
        from omnigen.detector.model.checkpoint import load_checkpoint
        from omnigen.detector.data.samples import split_frames
        from omnigen.detector.prediction.predict import EVAL_MAX_DET

        stage = load_checkpoint(out / "last.pt").get("crop_stage")
        recipe = run_recipe(args, keys)
        imgsz = recipe.model.imgsz
        preds = predict_test_split(run, out, uov, recipe, args.device)
        report_path = out / "eval.json"
        run(["eval", str(preds), str(uov), "--split", "test", "--baseline", "--out", str(report_path)], report_path)
        report = json.loads(report_path.read_text())
        row = synthetic_row(report)
        baseline = synthetic_row({"report": report["baseline"]}) if "baseline" in report else None
        predictions = json.loads(preds.read_text())  # tens of MB: read once
        orders = asdict(corner_order_counts(uov_ds, predictions))
        hist = list(csv.DictReader((out / "results.csv").read_text().splitlines()))
        curve = [{"epoch": int(float(h["epoch"])), "oks_map50_95": float(h["oks_map50_95"]), "ap_oks50": float(h["ap_oks50"])}
                 for h in hist if h.get("oks_map50_95") not in (None, "", "nan")]
        entry = {"name": name, "train_args": [*keys, *options], "imgsz": imgsz,
                 "crop": recipe.data.window if 0 < recipe.data.window < imgsz else None,
                 "train_seconds": round(t, 1),
                 # robust to a busy machine where the total is not: the training part of an epoch
                 "median_epoch_seconds": round(statistics.median(float(h["seconds"]) for h in hist), 1),
                 "synthetic_test": row, "overall_test": report["report"]["rows"][0], "epochs_logged": len(hist),
                 "baseline_synthetic_test": baseline,
                 "curve": curve, "validated_on": validated_on(dataset, list(options), uov),
                 "predicted": (out / "predicted").read_text().strip(),
                 **detection_cap_counts(predictions, len(split_frames(uov, "test") or []), EVAL_MAX_DET),
                 "report_rows": report["report"]["rows"], "corner_order": orders, "crop_stage": stage}
        runs.append(entry)
        return entry

    main_run = train_eval("n-p2", [])  # the recipe: nano with P2
    for scale in args.scales[1:]:
        train_eval(f"{scale}-p2", [f"model.scale={scale}"])
    if "no-p2" in args.ablations:
        train_eval("n-no-p2", ["model.p2=false"])
    if "hires" in args.ablations:
        hires = int(run_recipe(args).model.imgsz * 1.5) // 32 * 32
        train_eval(f"n-p2-{hires}", [f"model.imgsz={hires}"])
    if "no-synthetic" in args.ablations:
        if not real:
            raise SystemExit("validate: the no-synthetic ablation needs --kitti or --dair")
        merged_real = work / "uov-real"
        run(["merge", *map(str, real), "--out", str(merged_real), "--test-fraction", "0.0"],
            merged_real / "manifest.json")
        train_eval("n-p2-no-synthetic", [], dataset=merged_real, options=["--val-split", "train"])

    bev_dir = work / "bev"
    # one detection a box: the evaluation's class copies would stand twice on the map
    from omnigen.detector.prediction.predict import one_label_per_box

    predictions = work / "runs" / "n-p2" / "bev-predictions.json"
    atomic_write_text(predictions, json.dumps(one_label_per_box(json.loads(
        (work / "runs" / "n-p2" / "test-predictions.json").read_text()))))
    bev_stamp = hashlib.sha256(predictions.read_bytes()).hexdigest()  # the BEV of these predictions
    if stale(bev_dir / "done", bev_stamp):
        shutil.rmtree(bev_dir)
        run.forget(bev_dir)
    run(["bev", str(predictions), "--out", str(bev_dir), "--score-thr", "0.3", "--no-draw"], bev_dir / "done")
    bev_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(bev_dir / "done", bev_stamp + "\n")

    counts = json.loads((uov / "manifest.json").read_text())
    wall = sum(c["seconds"] for c in run.log)  # every stage, over resumed invocations too
    row = main_run["synthetic_test"]
    results = {
        "oks_map50_95": row["oks_map50_95"], "ap_oks50": row["ap_oks50"], "precision": row["precision"],
        "recall": row["recall"], "f1": row["f1"], "bev_adherence_deg": row["ground_adherence_deg"],
        "corner_error_px": row.get("corner_error_px"), "corner_error_rel": row.get("corner_error_rel"),
        # the box-template baseline's synthetic row: what the 2D boxes alone give (omnigen eval --baseline)
        "baseline": {k: (main_run["baseline_synthetic_test"] or {}).get(k) for k in BASELINE_FIELDS},
        "targets": {"oks_map50_95": TARGET_MAP, "bev_adherence_deg": TARGET_ADHERENCE},
        "frames": {"total": counts["counts"]["frames"], "by_source": counts["counts"]["frames_by_source"],
                   "by_view": counts["counts"]["frames_by_view"], "objects": counts["counts"]["objects"],
                   "splits": counts.get("splits")},
        "wall_seconds": round(wall, 1), "machine": machine(),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "arguments": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        "runs": runs, "commands": run.log, "test_object_sizes": object_sizes(uov_ds),
        "by_view": [g for g in main_run["report_rows"] if g["group"].startswith("view=")],
        "by_class": [g for g in main_run["report_rows"] if g["group"].startswith("class=")],
        "size_bins_px": SIZE_BINS,
        # what the evaluation gives the truth's own corners: the floor under the model's figures
        "adherence_floor": floor_rows(uov_ds, "test", FLOOR_NOISE_PX, args.seed),
    }
    args.results.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.results / "results.json", results, indent=2)
    md = args.results / "RESULTS.md"
    atomic_write_text(md, results_markdown(results) + kept_sections(md.read_text() if md.exists() else ""))
    print(f"validate: wrote {args.results / 'RESULTS.md'} and results.json in {wall / 60:.1f} min")
    print(f"synthetic test: OKS mAP50:95 {row['oks_map50_95']:.3f} (target >= {TARGET_MAP}), "
          f"ground-plane adherence {row['ground_adherence_deg']} deg (target <= {TARGET_ADHERENCE})")
    return 0


def object_sizes(ds: Dataset, split: str = "test") -> dict[str, dict[str, float]]:
    """Per view of `split`: objects, the 10th/50th/90th percentile of sqrt(box area) in pixels and
    the median distance from the camera to the box centre in metres.

    Why in the report: OKS judges a corner against the object's scale, so the same model scores
    far lower on 12-pixel objects than on 60-pixel ones; these say how hard the test split is.
    """
    import numpy as np

    from omnigen.splits import read_split

    frames = np.zeros(len(ds), dtype=bool)
    frames[[ds.index_of(f) for f in read_split(ds.root, split)]] = True
    o = ds.objects
    keep = frames[o.frame]
    size = np.sqrt((o.bbox[:, 2] - o.bbox[:, 0]) * (o.bbox[:, 3] - o.bbox[:, 1]))[keep]
    distance = np.linalg.norm(o.center, axis=1)[keep]
    views = np.asarray(ds.table.view, dtype=object)[o.frame][keep]
    out = {}
    for view in sorted(set(views.tolist())):
        v = size[views == view]
        p10, p50, p90 = np.percentile(v, [10, 50, 90]).tolist()
        out[view] = {"objects": int(len(v)), "p10_px": round(p10, 1), "p50_px": round(p50, 1), "p90_px": round(p90, 1),
                     "p50_m": round(float(np.median(distance[views == view])), 1)}
    return out


def baseline_table(r: dict[str, Any]) -> list[str]:
    """The model beside the box-template baseline (each predicted box's corners placed by the mean
    layout of its class and view, learned from the train split): whether the corners carry more
    than the 2D box does. Empty for results written before the baseline existed."""
    b = r.get("baseline")
    if not b:
        return []
    rows = [("OKS mAP50:95", "oks_map50_95", r["oks_map50_95"], 3), ("AP at OKS 0.50", "ap_oks50", r["ap_oks50"], 3),
            ("ground-plane adherence (deg)", "ground_adherence_deg", r["bev_adherence_deg"], 2),
            ("median corner error of box-matched objects (px)", "corner_error_px", r.get("corner_error_px"), 2),
            ("the same, relative to sqrt(box area)", "corner_error_rel", r.get("corner_error_rel"), 3)]
    return ["## The corners against what the boxes alone give", "",
            "The same predictions with their corners replaced by the box-template baseline",
            "(`omnigen eval --baseline`, docs/metric-3d.md): where the model is not better, its corners",
            "carry no more than its 2D boxes.", "",
            "| synthetic test split | model | box-template baseline |", "|---|---|---|",
            *[f"| {name} | {fmt(v, d)} | {fmt(b.get(k), d)} |" for name, k, v, d in rows],
            ""]


def _view_line(g: dict[str, Any], sizes: dict[str, Any]) -> str:
    """One row of the by-view table: the view's metrics and how large its test objects are."""
    px = " / ".join(str(sizes.get(k, "-")) for k in ("p10_px", "p50_px", "p90_px"))
    adherence = f"{fmt(g.get('ground_adherence_deg'), 2)} ({g.get('adherence_objects', 0)})"
    return (f"| {g['group'][5:]} | {fmt(g['oks_map50_95'])} | {fmt(g['ap_oks50'])} | {fmt(g['f1'])} | {adherence} | "
            f"{sizes.get('objects', '-')} | {px} | {sizes.get('p50_m', '-')} |")


def size_table(r: dict[str, Any]) -> list[str]:
    """Every run's mAP per object size: the P2 level (stride 4) is there for the smallest objects."""
    bins = r.get("size_bins_px") or {}
    rows = {run["name"]: {g["group"][5:]: g for g in run.get("report_rows", []) if g["group"].startswith("size=")}
            for run in r["runs"]}
    # smallest first, whatever order results.json keeps the bins in (JSON written with sorted keys)
    names = sorted((b for b in bins if any(b in by for by in rows.values())), key=lambda b: tuple(bins[b]))
    if not names:
        return []
    label = {b: f"< {hi:g}" if lo == 0 else f">= {lo:g}" if hi >= 1e4 else f"{lo:g}-{hi:g}"
             for b, (lo, hi) in bins.items()}
    objects = {b: next((by[b]["objects"] for by in rows.values() if b in by), "-") for b in names}
    lines = ["## By object size, every run", "",
             "Over the whole test split; size is the square root of the 2D box area in pixels, in bins",
             "evaluated as pycocotools' own area ranges (detector/evaluation/oks_eval.py). Each cell: mAP50:95 / AP50.",
             "",
             "| run | " + " | ".join(f"{b}: {label[b]} px ({objects[b]} objects)" for b in names) + " |",
             "|---|" + "---|" * len(names)]
    for name, by in rows.items():
        cells = [f"{fmt(by[b]['oks_map50_95'])} / {fmt(by[b]['ap_oks50'])}" if b in by else "-" for b in names]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def validated_on(dataset: Path, train_args: list[str], merged: Path) -> str:
    """The split a run's periodic validation read, as train resolves it (--val-split, else val,
    else test); named with its dataset when that is not `merged`, whose test split the tables use."""
    from omnigen.detector.training.train import resolve_val_split

    given = train_args[train_args.index("--val-split") + 1] if "--val-split" in train_args else None
    split = resolve_val_split(str(dataset), given) or "all"
    return split if dataset == merged else f"{split} of {dataset.name}"


def curve_table(r: dict[str, Any]) -> list[str]:
    """The test split's OKS mAP50:95 at each periodic validation of the runs that validated on it:
    whether a run had stopped improving when its schedule ended, or more steps would lift it."""
    runs = [run for run in r["runs"] if run.get("curve") and run.get("validated_on") == "test"]
    if not runs:
        return []
    epochs = sorted({c["epoch"] for run in runs for c in run["curve"]})
    at = {run["name"]: {c["epoch"]: c for c in run["curve"]} for run in runs}
    left = [run["name"] for run in r["runs"] if run.get("curve") and run not in runs]
    lines = ["## How the test score grew while training", "",
             "The training validated its EMA weights on the test split every `--val-every` epochs; each cell:",
             "mAP50:95 / AP50 over the whole test split. The learning rate decays along a cosine to",
             "1% of its peak, so a curve flat at its end had settled within this schedule, not converged",
             "for good: a longer schedule (more steps) starts that decay later."
             + (f" Left out: {', '.join(left)} (validated on another split)." if left else ""),
             "",
             "| epoch | " + " | ".join(run["name"] for run in runs) + " |",
             "|---|" + "---|" * len(runs)]
    for e in epochs:
        cells = [f"{fmt(at[n][e]['oks_map50_95'])} / {fmt(at[n][e]['ap_oks50'])}" if e in at[n] else "-" for n in at]
        lines.append(f"| {e} | " + " | ".join(cells) + " |")
    return lines


def upsampled_note(r: dict[str, Any]) -> list[str]:
    """The lines that say so when a run's input is larger than the rendered frames: the hires
    ablation then magnifies the objects relative to the strides, but adds no detail."""
    size = r["arguments"].get("size")
    bigger = [run for run in r["runs"] if size and run["imgsz"] > size]
    if not bigger:
        return []
    names = ", ".join(run["name"] for run in bigger)
    return [f"The frames were rendered at {size} x {size}; {names} letterboxed them to a larger input, so its",
            "objects cover more cells of each stride, upsampled: it gains no detail a larger render would have.",
            ""]


def window_note(r: dict[str, Any]) -> list[str]:
    """The lines that say so when runs trained on windows of the same size cut from inputs of
    different sizes: each step then shows a run with a larger input less of each image, so it sees
    fewer objects in as many steps, a difference beside the resolution (`data.window=0` has none)."""
    shares: dict[float, list[str]] = {}
    for run in r["runs"]:
        if run.get("crop"):
            shares.setdefault(min(1.0, (run["crop"] / run["imgsz"]) ** 2), []).append(run["name"])
    if len(shares) < 2:
        return []
    parts = "; ".join(f"{', '.join(names)}: {share:.0%}" for share, names in sorted(shares.items(), reverse=True))
    return ["The runs trained on windows of one size cut from their inputs (`data.window`), so a larger input",
            f"showed fewer objects a step; the share of the input a window holds: {parts}.",
            "The comparison mixes resolution with objects seen; `data.window=0` (whole images) has no such difference.",
            ""]


def floor_table(r: dict[str, Any]) -> list[str]:
    """The adherence floor section (benchmarks/bench_adherence_floor.py), when results.json has it."""
    rows = r.get("adherence_floor")
    if not rows:
        return []
    groups = list(dict.fromkeys(x["group"] for x in rows))
    cell = {(x["noise_px"], x["group"]): x for x in rows}
    lines = ["## What the truth's own corners score", "",
             "The same evaluation handed the test objects' true projected corners as predictions, exact and",
             "with Gaussian noise on each coordinate (benchmarks/bench_adherence_floor.py): the adherence",
             "the metric gives a perfect model (it lifts with the class's median size, not the object's),",
             "and how near to exact the corners must be for the targets. Each cell: mAP50:95 / adherence (deg).",
             "",
             "| noise (px) | " + " | ".join(g.replace("source=", "").replace("view=", "") for g in groups) + " |",
             "|---|" + "---|" * len(groups)]
    for noise in dict.fromkeys(x["noise_px"] for x in rows):
        lines.append(f"| {noise:g} | " + " | ".join(
            f"{fmt(cell[noise, g]['oks_map50_95'])} / {fmt(cell[noise, g]['adherence_deg'], 2)}"
            if (noise, g) in cell else "-" for g in groups) + " |")
    return lines + [""]


def command_line(a: dict[str, Any]) -> str:
    """The validate command that `a` (results.json's arguments) stand for: the options whose value
    is not the script's default (results.json keeps every value)."""
    defaults = vars(build_parser().parse_args([]))

    def opt(k: str, v: Any) -> str:
        flag = f"--{k.replace('_', '-')}"
        if isinstance(v, bool):
            return flag if v else f"--no-{k.replace('_', '-')}"
        return f"{flag} {' '.join(map(str, v))}" if isinstance(v, list) else f"{flag} {v}"

    def said(k: str, v: Any) -> bool:  # identity, not equality: 0 and 0.0 are values to print (0 == False)
        if k in defaults and (v == defaults[k] and type(v) is type(defaults[k])):
            return False
        if v is False:  # a switch turned off: said where it is on by default (--no-cache)
            return defaults.get(k) is True
        return k != "fresh" and v is not None and not (isinstance(v, list) and not v)

    return " ".join(["python benchmarks/validate.py", *(opt(k, v) for k, v in a.items() if said(k, v))])


def detection_cap_counts(preds: list[dict[str, Any]], frames: int, cap: int) -> dict[str, int]:
    """How many of the `frames` predicted reached `cap` detections (predict's EVAL_MAX_DET): where
    they do, lower-scoring detections were cut, objects among them (multi-label copies take places
    too)."""
    from collections import Counter

    per_frame = Counter(p.get("frame_id", p["image_id"]) for p in preds)
    return {"detection_cap": cap, "test_frames_predicted": frames,
            "frames_at_detection_cap": sum(1 for c in per_frame.values() if c >= cap)}


def protocol_line(r: dict[str, Any]) -> list[str]:
    """How the main run's test predictions were made (predict_stage's marker); none for a
    results.json older than the marker."""
    run = (r.get("runs") or [{}])[0]
    made = run.get("predicted")
    if not made:
        return []
    how = ("every class an anchor rates above the 0.001 floor is a detection (multi-label, as Ultralytics' "
           "validation scores)" if "multi_label=True" in made else "one class an anchor, its best (single-label)")
    capped = "" if "frames_at_detection_cap" not in run else (
        f"; {run['frames_at_detection_cap']} of {run['test_frames_predicted']} frames reached the cap of "
        f"{run['detection_cap']} detections")
    stage = run.get("crop_stage")
    snapped = ("; each image's vertical edges turned to its vertical vanishing point, found from the detections "
               "and the image's line segments (predict.vertical=lines)" if "vertical='lines'" in made else "")
    lines = [f"- test predictions: {how}; last.pt, not best.pt{capped}{snapped}"]
    if stage:
        sc = stage.get("score", {})
        told = ", told where each crop was cut (crop_stage.position)" if stage.get("position") else ""
        gain = stage.get("config", {}).get("offset_gain")
        told += f", an L1 term on the faces' offset (crop_stage.offset_gain={gain:g})" if gain else ""
        how = "the run's second phase" if stage.get("by") == "omnigen train" else "`omnigen train-crop`"
        lines.append(f"- crop stage: trained again apart from the detector ({how}, "
                     f"{stage['steps_done']} steps, {stage['seconds']} s{told}) and predicted with (the detector's "
                     f"other tensors unchanged); on its {stage.get('score_split')} crops about moved boxes: corner error rel "
                     f"{fmt(sc.get('corner_rel'))}, front right {fmt(sc.get('front'))}, class accuracy "
                     f"{fmt(sc.get('class_acc'))}")
    return lines


def results_markdown(r: dict[str, Any]) -> str:
    """RESULTS.md: every number below is read from results.json, written by this script."""
    a = r["arguments"]
    cmd = command_line(a)
    lines = [
        "# Results: the data, validated end to end",
        "",
        "Written by `benchmarks/validate.py` (`make validate`); every number here is in `docs/results.json`,",
        "which the same run wrote. Rerun it to reproduce; the script's docstring says how to scale it up.",
        "",
        f"- command: `{cmd}` (every other option at its default; results.json lists them all)",
        f"- machine: {r['machine']}",
        f"- date: {r['date']}; {r['wall_seconds'] / 60:.1f} min of stage time (the sum of the stages below; "
        f"renders run {a['jobs']} at a time, so less elapsed)",
        f"- frames: {r['frames']['total']} ({', '.join(f'{k} {v}' for k, v in (r['frames']['by_source'] or {}).items())}); "
        f"{r['frames']['objects']} objects; split frames "
        f"{ {k: v['frames'] for k, v in (r['frames']['splits'] or {}).items()} }",
        *protocol_line(r),
        "",
        "## Nano with P2 on the synthetic test split",
        "",
        "| metric | value | target |",
        "|---|---|---|",
        f"| OKS mAP50:95 | {fmt(r['oks_map50_95'])} | >= {r['targets']['oks_map50_95']} |",
        f"| AP at OKS 0.50 | {fmt(r['ap_oks50'])} | |",
        f"| precision / recall / F1 at OKS 0.5 (best-F1 confidence) | {fmt(r['precision'])} / {fmt(r['recall'])} / {fmt(r['f1'])} | |",
        f"| ground-plane adherence of predicted corners (deg) | {fmt(r['bev_adherence_deg'], 2)} | <= {r['targets']['bev_adherence_deg']} |",
        "",
        *baseline_table(r),
        "## By view, and how large the test objects are",
        "",
        "OKS measures a corner's error against the object's scale (sqrt of its box area), so small",
        "objects need near-pixel-exact corners; the sizes are those of the test split's boxes. The",
        "adherence is that of the view's OKS-matched predictions (their number in brackets); the",
        "figure above is the mean over all three views' matches.",
        "",
        "| view | mAP50:95 | AP50 | F1 | adherence, deg (matches) | test objects | sqrt(area) px: 10th / median / 90th percentile | median distance (m) |",
        "|---|---|---|---|---|---|---|---|",
        *[_view_line(g, r["test_object_sizes"].get(g["group"][5:], {})) for g in r.get("by_view", [])],
        "",
        *floor_table(r),
        "## By class",
        "",
        "Over the whole test split (synthetic and real frames). mAP50:95 above is the mean of these",
        "rows over classes, so a rare class weighs as much as cars do.",
        "",
        "| class | test objects | mAP50:95 | AP50 | precision | recall | F1 |",
        "|---|---|---|---|---|---|---|",
        *[f"| {g['group'][6:]} | {g['objects']} | {fmt(g['oks_map50_95'])} | {fmt(g['ap_oks50'])} | "
          f"{fmt(g['precision'])} | {fmt(g['recall'])} | {fmt(g['f1'])} |" for g in r.get("by_class", [])],
        "",
        "## Every run (the design's Tables 2 and 8, as far as this machine allowed)",
        "",
        f"Scales trained: {', '.join(a['scales'])}; ablations: {', '.join(a['ablations']) or 'none in this run'} "
        "(`--ablations no-p2 hires no-synthetic`, `--scales n s m` add the others).",
        "",
        "Each run is evaluated on the test split with its last weights (`last.pt`): without a val split",
        "the training's periodic validation reads the test split, so picking its best checkpoint would",
        "flatter the number. Each row is one training with one seed.",
        "",
        *upsampled_note(r),
        *window_note(r),
        "Train time is the training's wall time (a run cut off and resumed counts the epochs it kept",
        "from before the cut, not the work the cut threw away); the median epoch is that of an epoch's",
        "steps alone (no validation), the figure to compare when the machine was busy at times.",
        "",
        "| run | train args | input (training crop) | train time (s) | median epoch (s) | synthetic mAP50:95 | AP50 | F1 | adherence (deg) | overall mAP50:95 |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run in r["runs"]:
        s, o = run["synthetic_test"], run["overall_test"]
        size = f"{run['imgsz']} ({run['crop']})" if run.get("crop") else str(run["imgsz"])
        args = f"`{' '.join(run['train_args'])}`" if run["train_args"] else "the recipe"
        lines.append(f"| {run['name']} | {args} | {size} | {run['train_seconds']} | "
                     f"{run.get('median_epoch_seconds', '-')} | "
                     f"{fmt(s['oks_map50_95'])} | {fmt(s['ap_oks50'])} | {fmt(s['f1'])} | {fmt(s['ground_adherence_deg'], 2)} | "
                     f"{fmt(o['oks_map50_95'])} |")
    sizes = size_table(r)
    if sizes:
        lines += ["", *sizes]
    curves = curve_table(r)
    if curves:
        lines += ["", *curves]
    lines += ["", "## Front or back: which corner order fits the predictions",
              "",
              "Each test object is matched to the best-scoring prediction (score >= 0.2) whose 2D box",
              "overlaps its own by IoU >= 0.5, blind to the corners; then the order of the eight corners",
              "that brings the prediction closest is counted (detector/evaluation/corner_order.py). `turned 180`",
              "means front and rear swapped: the object was found, its heading was not.",
              "",
              "| run | matched objects | unmatched | as labelled | turned 180 | mirrored | turned +90 | turned -90 |",
              "|---|---|---|---|---|---|---|---|"]
    for run in r["runs"]:
        c = run.get("corner_order")
        if c:
            share = lambda n: f"{c['best'][n]} ({c['best'][n] / c['matched']:.0%})" if c["matched"] else "-"  # noqa: E731
            lines.append(f"| {run['name']} | {c['matched']} | {c['unmatched']} | "
                         + " | ".join(share(n) for n in ("as labelled", "turned 180", "mirrored", "turned +90", "turned -90"))
                         + " |")
    lines += ["", "## Commands and their wall times", "",
              "The load is the 1-minute load average as the command ended; the CPU share, for a command run "
              "in validate's own process, the share of the usable cores' time it used: a training that had "
              "the machine to itself reads a share near 1 and a load near the cores' number.", "",
              "| command | seconds | CPU share | load |", "|---|---|---|---|"]
    lines += [f"| `{c['command']}` | {c['seconds']} | {c.get('cpu_share', '-')} | {c.get('load', '-')} |"
              for c in r["commands"]]
    lines += [""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
