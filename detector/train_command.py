"""Train the bundled keypoint detector on an UrbanOmniView dataset (CPU, one GPU, or torchrun)."""

from __future__ import annotations

import argparse
import sys
import time

from omnigen.options import fraction, integer, number

SEED_MAX = 2**32 - 1
"""Training's seeds are mixed with the epoch into torch generator seeds (seed * 100003 + epoch)
that must stay within 64 bits."""
GAIN_MAX = 1000.0
"""Largest loss gain accepted: a term weighed more than that drowns every other one."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="UrbanOmniView dataset folder (splits from omnigen merge)")
    p.add_argument("--out", required=True,
                   help="run folder: last.pt, best.pt, args.json, results.csv; one that holds a run is refused "
                        "without --resume or --fresh")
    p.add_argument("--model", default="n", choices=["n", "s", "m", "l", "x"], help="width and depth scale")
    p.add_argument("--backbone", default="c3k2", help="backbone family: c3k2 (YOLO11-style) or c2f (YOLOv8-style)")
    p.add_argument("--p2", action=argparse.BooleanOptionalAction, default=True, help="stride-4 level for small objects")
    p.add_argument("--p6", action="store_true", help="add a stride-64 level")
    p.add_argument("--imgsz", type=integer(32, 8192), default=640, help="input size: images are letterboxed to it (validation and prediction too)")
    p.add_argument("--crop", type=integer(32, 8192), default=None,
                   help="train on random CROP x CROP windows of the IMGSZ input: objects keep the scale they are "
                        "predicted at, for (CROP/IMGSZ)^2 of the pixels per step")
    p.add_argument("--crop-focus", type=fraction(), default=0.0, metavar="P",
                   help="with --crop: centre this share of the windows on an object drawn class-balanced "
                        "(weight 1 / its class's training instances; detector/balance.py)")
    p.add_argument("--repeat-thresh", type=fraction(), default=0.0, metavar="T",
                   help="repeat-factor sampling (LVIS): a frame whose rarest class is in a fraction f < T of the "
                        "training frames is drawn sqrt(T / f) times an epoch; 0: off")
    p.add_argument("--cache", action="store_true",
                   help="decode and letterbox every image once and keep it in memory (train and val splits; "
                        "refused when it would not fit)")
    p.add_argument("--epochs", type=integer(1, 100_000), default=100)
    p.add_argument("--batch", type=integer(1, 4096), default=16, help="total batch over all processes")
    p.add_argument("--optimizer", default="adamw", choices=["adamw", "adam"],
                   help="adamw (decoupled weight decay) or adam (weight decay in the gradient)")
    p.add_argument("--lr0", type=number(0.0, 1.0, lo_open=True), default=2e-3, help="peak learning rate (cosine decay to lr0 * lrf)")
    p.add_argument("--lrf", type=fraction(), default=0.01, help="final learning rate, a fraction of lr0")
    p.add_argument("--taxonomy", default="fine", help="class taxonomy preset or TOML file")
    p.add_argument("--train-split", default="train")
    p.add_argument("--val-split", default=None, help="default: val if present, else test, else all frames")
    p.add_argument("--out-of-image", default="learn", choices=["learn", "drop"],
                   help="corners outside the image but in front of the camera: learn them (default) or mask them")
    p.add_argument("--no-augment", action="store_true", help="letterbox only (flip, scale, colour off)")
    p.add_argument("--val-every", type=integer(0, 100_000), default=1, help="validate every N epochs (and after the last); 0: never")
    p.add_argument("--workers", type=integer(0, 256), default=2, help="data loader processes")
    p.add_argument("--seed", type=integer(0, SEED_MAX), default=0)
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: cuda when present)")
    p.add_argument("--kpt-sigma-start", type=number(0.0, 10.0, lo_open=True), default=0.5, help="keypoint-loss sigma at the start")
    p.add_argument("--kpt-sigma-end", type=number(0.0, 10.0, lo_open=True), default=0.125,
                   help="keypoint-loss sigma after the anneal: the design's 0.125; 0.25 is the OKS metric's kernel")
    p.add_argument("--kpt-sigma-anneal", type=fraction(), default=0.3, help="fraction of the run the anneal takes")
    p.add_argument("--kpt-mode", default="anchor", choices=["anchor", "box"],
                   help="corners as offsets from the anchor, or in units of the anchor's predicted box")
    front = p.add_mutually_exclusive_group()  # two answers to which face is the front: one at a time
    front.add_argument("--kpt-turn", action="store_true",
                   help="learn corners up to the 180-degree turn, the turn as a class of its own (loss.turn_targets)")
    front.add_argument("--kpt-heading", action="store_true",
                   help="learn corners up to the 180-degree turn and the front from a regressed image heading "
                        "(detector/heading.py); --kpt-labelled and --kpt-turn-start apply as with --kpt-turn")
    p.add_argument("--heading-gain", type=number(0.0, GAIN_MAX), default=None,
                   help="with --kpt-heading: gain of the heading term (default 1)")
    p.add_argument("--heading-crop", type=integer(0, 1024), default=0, metavar="PX",
                   help="place each object's corners and read its front from a PX x PX crop of it with a small "
                        "second-stage CNN (detector/crop_stage.py; 64 is what benchmarks/crop_layout.py and "
                        "heading_visibility.py measure); 0: none")
    p.add_argument("--crop-classes", action="store_true",
                   help="with --heading-crop: the crop stage names each crop's class too, and prediction rescores "
                        "each refined detection by it, sqrt(score * p[class]) (detector/crop_stage.py)")
    p.add_argument("--crop-split", action="store_true",
                   help="with --crop-classes: the classes from a crop net of their own, not the corners' "
                        "(crop_stage.SplitCropNet; twice the stage's cost)")
    p.add_argument("--kpt-hidden", type=integer(8, 4096), default=None,
                   help="keypoint-branch width (default: max(stride-8 width / 4, 24), as Ultralytics' pose head)")
    p.add_argument("--kpt-labelled", type=number(0.0, GAIN_MAX), default=0.0,
                   help="with --kpt-turn: gain of the OKS loss in the labelled order, a pull towards the true heading")
    p.add_argument("--kpt-turn-start", type=fraction(), default=0.0,
                   help="with --kpt-turn: fraction of the run in which corners are compared as labelled only")
    p.add_argument("--kpt-l1", type=number(0.0, GAIN_MAX), default=0.0,
                   help="gain of a scale-free L1 corner term beside the OKS keypoint loss (0: the design's loss)")
    p.add_argument("--amp", default="auto", choices=["auto", "bf16", "fp16", "off"],
                   help="mixed precision of the forward pass (auto: fp16 on CUDA, off on the CPU; bf16 "
                        "steps take about 0.65 of the time on CPUs with AVX512-BF16, less precisely)")
    p.add_argument("--time", type=number(0.0, 1e6, lo_open=True), default=None, metavar="MINUTES",
                   help="wall-clock budget of the whole run: the schedule (warm-up, cosine, sigma anneal, "
                        "validations) is fitted to the epochs that fit, --epochs is then an upper bound")
    p.add_argument("--weights", default=None, metavar="PATH",
                   help="start from an earlier run's weights (best.pt/last.pt): a new run with a fresh optimiser; "
                        "class branches re-initialised where the classes differ")
    p.add_argument("--channels-last", action=argparse.BooleanOptionalAction, default=None,
                   help="NHWC activations (default: on for CUDA, off on the CPU)")
    again = p.add_mutually_exclusive_group()  # what to do with a run already in --out
    again.add_argument("--resume", action="store_true",
                       help="continue OUT/last.pt with the run's own settings: any other setting given differently "
                            "is refused, but --device, --workers and --cache (to train longer, start a new run "
                            "from its weights with --weights)")
    again.add_argument("--fresh", action="store_true",
                       help="delete the run in OUT (its last.pt, best.pt, results.csv and args.json; a folder that "
                            "also holds other files is refused) and start over")


def run(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from omnigen.detector.data import Augment
    from omnigen.detector.train import TrainConfig, train
    from omnigen.progress import print_table

    if args.heading_gain is not None and not args.kpt_heading:
        raise ValueError("--heading-gain weighs the heading of --kpt-heading, which is not given")
    if args.crop_classes and not args.heading_crop:
        raise ValueError("--crop-classes names classes in the crop stage of --heading-crop, which is not given")
    if args.crop_split and not args.crop_classes:
        raise ValueError("--crop-split gives the classes of --crop-classes a net of their own; --crop-classes is not given")
    cfg = TrainConfig(
        dataset=str(args.dataset), out=str(args.out), model=args.model, backbone=args.backbone, p2=args.p2,
        p6=args.p6, imgsz=args.imgsz, crop=args.crop, crop_focus=args.crop_focus,
        repeat_thresh=args.repeat_thresh, cache=args.cache, epochs=args.epochs, batch=args.batch,
        optimizer=args.optimizer, lr0=args.lr0, lrf=args.lrf,
        taxonomy=args.taxonomy, train_split=args.train_split, val_split=args.val_split,
        out_of_image=args.out_of_image, augment=asdict(Augment.off() if args.no_augment else Augment()),
        workers=args.workers, seed=args.seed, device=args.device, val_every=args.val_every,
        kpt_sigma_start=args.kpt_sigma_start, kpt_sigma_end=args.kpt_sigma_end, kpt_sigma_anneal=args.kpt_sigma_anneal,
        kpt_mode=args.kpt_mode, kpt_l1=args.kpt_l1, kpt_turn=args.kpt_turn, kpt_hidden=args.kpt_hidden,
        kpt_labelled=args.kpt_labelled, kpt_turn_start=args.kpt_turn_start, kpt_heading=args.kpt_heading, heading_crop=args.heading_crop, crop_classes=args.crop_classes, crop_split=args.crop_split, heading_gain=1.0 if args.heading_gain is None else args.heading_gain, amp=args.amp,
        time_minutes=args.time, weights=args.weights, channels_last=args.channels_last)
    start = time.perf_counter()

    def report(epoch: int, row: dict) -> None:
        parts = " ".join(f"{k}={row[k]:.4f}" for k in ("box", "dfl", "cls", "kpt", "kvis", "oks_map50_95") if k in row)
        print(f"epoch {epoch + 1}: {parts} ({row['seconds']:.1f} s)", file=sys.stderr, flush=True)

    last = train(cfg, resume=args.resume, on_epoch=report, fresh=args.fresh)
    if last:
        print_table(f"omnigen train: {args.out}", ["metric", "value"],
                    [(k, v) for k, v in last.items()] + [("wall time (s)", time.perf_counter() - start)])
    return 0
