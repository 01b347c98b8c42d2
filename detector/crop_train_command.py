"""Train a detector's crop stage apart from it, on clean crops of the labelled objects (detector/training/crop_train.py).

    omnigen train-crop runs/uov --weights runs/n-p2/last.pt --out runs/n-p2/crop.pt

`omnigen train` does this as its second phase, with the recipe's crop_stage keys (detector/recipe.py,
whose values are these options' defaults); this command runs that phase alone, again. OUT is the
detector's checkpoint with its crop stage (corners, front and, by default, classes)
replaced by one trained here: `omnigen predict`, `eval` and `bev` take it as they take the
detector's own. The input checkpoint is never written. A rerun of the same arguments whose OUT
exists does nothing; one that was stopped goes on from OUT.partial.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from omnigen.options import fraction, integer, number, seed


def add_arguments(p: argparse.ArgumentParser) -> None:
    from omnigen.detector.training.crop_train_config import CropTrainConfig  # plain data: no torch for --help
    from omnigen.detector.recipe import RECIPE

    p.add_argument("dataset", help="UrbanOmniView dataset folder (splits from omnigen merge)")
    p.add_argument("--weights", required=True, help="the detector's checkpoint (best.pt or last.pt of omnigen train)")
    p.add_argument("--out", required=True, help="the checkpoint to write: the detector with the new crop stage")
    p.add_argument("--steps", type=integer(1, 10_000_000), default=CropTrainConfig.steps)
    p.add_argument("--batch", type=integer(1, 65536), default=CropTrainConfig.batch, help="crops a step")
    p.add_argument("--lr", type=number(0.0, 1.0, lo_open=True), default=CropTrainConfig.lr, help="peak learning rate of the one-cycle schedule")
    p.add_argument("--copies", type=integer(1, 1000), default=CropTrainConfig.copies,
                   help="crops per training object, each about its own moved box")
    p.add_argument("--balance", type=fraction(), default=CropTrainConfig.balance,
                   help="draw a crop with weight (crops of its class)^-BALANCE: 0 uniform, 1 every class equally")
    p.add_argument("--crop", type=integer(16, 1024), default=None, metavar="PX",
                   help="crop side (default: the checkpoint's stage's, else 64)")
    p.add_argument("--classes", action=argparse.BooleanOptionalAction, default=None,
                   help="the stage names each crop's class, and prediction rescores by it "
                        "(default: as the checkpoint's stage does; on for a checkpoint without one)")
    p.add_argument("--split", action=argparse.BooleanOptionalAction, default=RECIPE.crop_stage.split,
                   help="with classes: name them with a crop net of their own, not the corners' "
                        "(crop_stage.SplitCropNet)")
    p.add_argument("--position", action=argparse.BooleanOptionalAction, default=RECIPE.crop_stage.position,
                   help="tell the corners' net where each crop was cut from its input (crop_stage.crop_position): "
                        "the direction of an object's vertical edges depends on it")
    p.add_argument("--heading-gain", type=number(0.0, 1000.0), default=CropTrainConfig.heading_gain,
                   help="gain of the heading term beside the corners'")
    p.add_argument("--offset-gain", type=number(0.0, 1000.0), default=CropTrainConfig.offset_gain,
                   help="gain of an L1 term on the bottom face's offset from the top face (0: none)")
    p.add_argument("--amp", default=CropTrainConfig.amp, choices=["off", "bf16"],
                   help="bf16: the forward pass under CPU bfloat16 autocast")
    p.add_argument("--train-split", default="train")
    p.add_argument("--val-split", default=None, help="scored at the end (default: val if present, else test)")
    p.add_argument("--seed", type=seed(), default=CropTrainConfig.seed)
    p.add_argument("--threads", type=integer(0, 1024), default=0, help="torch threads (0: torch's default)")


def run(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    import torch

    from omnigen.detector.model.checkpoint import checkpoint_taxonomy, detector_config, load_checkpoint, save_checkpoint
    from omnigen.detector.training.crop_train import (attach_stage, cut_sets, detector_stage, new_stage, score_stage,
                                             stage_progress, stage_record, train_stage)
    from omnigen.detector.training.crop_train_config import CropTrainConfig
    from omnigen.detector.prediction.predict import trained_imgsz
    from omnigen.detector.training.train import resolve_val_split
    from omnigen.files import file_digest
    from omnigen.outputs import refuse_inputs
    from omnigen.progress import print_table

    weights, out = Path(args.weights), Path(args.out)
    refuse_inputs(out, [weights, args.dataset], "train-crop")  # by inode: a hard link to the weights counts
    refuse_inputs(out.with_name(out.name + ".partial"), [weights, args.dataset], "train-crop")
    if out.suffix != ".pt":
        raise ValueError(f"--out {out}: a checkpoint file name ending in .pt")
    state = load_checkpoint(weights)
    taxonomy = checkpoint_taxonomy(state)
    det = detector_config(weights, state)
    size = det.heading_crop or 64 if args.crop is None else args.crop
    if size <= 0 or size % 16:
        raise ValueError(f"--crop {size}: must be a positive multiple of 16 (the crop net halves it four times)")
    classes = args.classes if args.classes is not None else (det.crop_classes or not det.heading_crop)
    split = bool(classes and args.split)
    cfg = CropTrainConfig(steps=args.steps, batch=args.batch, lr=args.lr, copies=args.copies, balance=args.balance,
                          heading_gain=args.heading_gain, offset_gain=args.offset_gain, seed=args.seed, amp=args.amp)
    imgsz = trained_imgsz(state)
    # the detector's bytes too: a detector trained again into the same last.pt is another input
    call = {"trained": "apart", "weights": str(weights), "weights_sha256": file_digest(weights),
            "dataset": str(args.dataset), "train_split": args.train_split, "crop": size, "classes": classes,
            "split": split, "position": args.position, "imgsz": imgsz, "config": asdict(cfg)}
    if out.exists():
        recorded = load_checkpoint(out).get("crop_stage")  # read as the current schema: every field there
        done = recorded if isinstance(recorded, dict) else {}
        if {k: done.get(k) for k in call} == call:
            print(f"{out}: already trained with these arguments; delete it to train again")
            return 0
        raise ValueError(f"{out}: exists and was not trained with these arguments (its crop_stage: "
                         f"{ {k: done.get(k) for k in call} }); delete it or pick another --out")
    if args.threads:
        torch.set_num_threads(args.threads)
    val_name = args.val_split or resolve_val_split(str(args.dataset), None)
    scored_on = f"the {val_name} split" if val_name else "all frames, the training ones too (no val or test split)"
    start = time.perf_counter()
    sets = cut_sets(args.dataset, taxonomy, imgsz, args.train_split, val_name, size, cfg.copies, cfg.seed)
    print(f"crops: train {len(sets['train'])} ({cfg.copies} an object, split {args.train_split}), "
          f"{val_name} {len(sets['val'])} ({time.perf_counter() - start:.1f} s)", file=sys.stderr, flush=True)

    net = new_stage(size, len(taxonomy.classes) if classes else 0, cfg.seed, split, args.position)
    partial = out.with_name(out.name + ".partial")
    history = train_stage(sets["train"], net, cfg, partial=partial, on_step=stage_progress(cfg.steps, "train-crop"),
                          identity={k: v for k, v in call.items() if k != "config"})
    seconds = time.perf_counter() - start
    rows = []
    if det.heading_crop == size:  # the detector's own stage, scored on the same crops
        rows.append(("trained with the detector", score_stage(detector_stage(state, weights), sets["val"])))
    new = score_stage(net, sets["val"])
    rows.append(("trained apart", new))
    record = stage_record(call, history, seconds, new, val_name)
    save_checkpoint(out, attach_stage(state, net, size, record))
    partial.unlink(missing_ok=True)
    print_table(f"omnigen train-crop: {out} (crops about moved boxes of {scored_on})",
                ["stage", "objects", "corner rel", "front right", "class acc"],
                [(who, s.objects, s.corner_rel, s.front, s.class_acc) for who, s in rows])
    print(f"train-crop: {len(history)} steps in {seconds:.0f} s; {val_name or 'all'} corner rel {new.corner_rel:.3f}, "
          f"front {new.front:.3f}, class acc {new.class_acc:.3f}; wrote {out}")
    return 0
