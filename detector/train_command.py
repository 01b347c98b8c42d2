"""Train the bundled keypoint detector on an UrbanOmniView dataset (CPU, one GPU, or torchrun).

    omnigen train runs/uov --out runs/n-p2                        # the validated recipe, both phases
    omnigen train runs/uov loss.kpt_l1=1.5 data.window=0 --out runs/b   # recipe keys changed
    omnigen train runs/uov --recipe runs/n-p2/recipe.json --out runs/c  # an earlier run's recipe

What is learned is the recipe (detector/recipe.py): its defaults are the model docs/RESULTS.md
validates, trained in two phases, the detector and then its crop stage apart on clean crops. Its
keys are changed as KEY=VALUE words (listed at the end of --help), or read from a
recipe file (`--recipe`, such as the RUN/recipe.json every run writes), the keys given applied over
it. The options are where and how long the run goes.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from typing import Any

from omnigen.options import integer, number

SEED_MAX = 2**32 - 1
"""Training's seeds are mixed with the epoch into torch generator seeds (seed * 100003 + epoch)
that must stay within 64 bits."""
LONG_RUN_SECONDS = 3600.0
"""A run projected to take longer than this is told so after its first epoch, with --time."""


class KeysAnywhere(argparse.ArgumentParser):
    """A parser that takes KEY=VALUE words after the options too (`omnigen train DATA --out RUN
    loss.kpt_l1=1.5`): argparse reads positionals only where they stand together, and would refuse
    those as unrecognised arguments."""

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        namespace, extras = super().parse_known_args(args, namespace)
        keys = [a for a in extras if "=" in a and not a.startswith("-")]
        if keys and hasattr(namespace, "overrides"):
            namespace.overrides = [*(namespace.overrides or []), *keys]
            extras = [a for a in extras if a not in keys]
        return namespace, extras


def add_arguments(p: argparse.ArgumentParser) -> None:
    from omnigen.detector.recipe import RUN, describe

    p.__class__ = type("TrainParser", (KeysAnywhere, type(p)), {})
    # the keys' list keeps its lines (cli's HelpFormatter would fill them into one paragraph)
    p.formatter_class = type("RecipeHelp", (argparse.RawDescriptionHelpFormatter, p.formatter_class), {})
    p.epilog = describe()
    p.add_argument("dataset", help="UrbanOmniView dataset folder (splits from omnigen merge)")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                   help="recipe keys to change (listed below), after DATASET or the options")
    p.add_argument("--out", required=True,
                   help="run folder: last.pt, best.pt, recipe.json, args.json, results.csv; one that holds a run is "
                        "refused without --resume or --fresh")
    p.add_argument("--recipe", default=None, metavar="FILE",
                   help="start from this recipe file (an earlier run's recipe.json) instead of the validated one; "
                        "KEY=VALUE applies over it")
    p.add_argument("--epochs", type=integer(1, 100_000), default=RUN.epochs,
                   help="epochs of the detector's schedule (an upper bound under --time)")
    p.add_argument("--time", type=number(0.0, 1e6, lo_open=True), default=RUN.time_minutes, metavar="MINUTES",
                   help="wall-clock budget of the whole run: the detector's schedule is fitted to the epochs that fit "
                        "in its share, the crop stage's steps to what is left (detector/training/time_budget.py)")
    p.add_argument("--val-every", type=integer(0, 100_000), default=RUN.val_every,
                   help="validate every N epochs (and after the last); 0: never")
    p.add_argument("--device", default=RUN.device, help="cpu, cuda, cuda:1 (default: cuda when present)")
    p.add_argument("--workers", type=integer(0, 256), default=RUN.workers,
                   help="data loader processes (default: none on a CPU of 2 cores or fewer, whose step needs them "
                        "all; else 2)")
    p.add_argument("--amp", default=RUN.amp, choices=["auto", "bf16", "fp16", "off"],
                   help="mixed precision of the forward pass (auto: fp16 on CUDA, off on the CPU; bf16 on CPUs "
                        "that run it natively is faster, a little less precise); the crop stage follows bf16")
    p.add_argument("--cache", action="store_true", default=RUN.cache,
                   help="decode and letterbox every image once and keep it in memory (refused when it would not fit)")
    p.add_argument("--channels-last", action=argparse.BooleanOptionalAction, default=RUN.channels_last,
                   help="NHWC activations (default: on for CUDA, off on the CPU)")
    p.add_argument("--seed", type=integer(0, SEED_MAX), default=RUN.seed,
                   help=f"seed of the initialisation, the shuffling and the augmentation (default: {RUN.seed})")
    p.add_argument("--train-split", default="train", help="the split trained on")
    p.add_argument("--val-split", default=None, help="default: val if present, else test, else all frames")
    p.add_argument("--weights", default=None, metavar="PATH",
                   help="start from an earlier run's weights (best.pt/last.pt): a new run with a fresh optimiser; "
                        "class branches re-initialised where the classes differ")
    again = p.add_mutually_exclusive_group()  # what to do with a run already in --out
    again.add_argument("--resume", action="store_true",
                       help="continue OUT/last.pt (its crop stage phase too) with the run's own recipe and settings: "
                            "any given differently is refused, but --device, --workers and --cache")
    again.add_argument("--fresh", action="store_true",
                       help="delete the run in OUT (the files it wrote; a folder that also holds other files is "
                            "refused) and start over")


def config_of(args: argparse.Namespace) -> Any:
    """The TrainConfig of the command line: the recipe (--recipe, else the validated one) with the
    KEY=VALUE overrides, and the run's settings from the options."""
    from omnigen.detector.recipe import resolve, train_fields
    from omnigen.detector.training.train import TrainConfig

    recipe = resolve(args.recipe, args.overrides)
    return TrainConfig(dataset=str(args.dataset), out=str(args.out), **train_fields(recipe), epochs=args.epochs,
                       time_minutes=args.time, val_every=args.val_every, device=args.device, workers=args.workers,
                       amp=args.amp, cache=args.cache, channels_last=args.channels_last, seed=args.seed,
                       train_split=args.train_split, val_split=args.val_split, weights=args.weights)


def run(args: argparse.Namespace) -> int:
    from omnigen.detector.training.train import train
    from omnigen.progress import print_table

    cfg = config_of(args)
    start = time.perf_counter()
    seconds: list[float] = []

    def report(epoch: int, row: dict) -> None:
        parts = " ".join(f"{k}={row[k]:.4f}" for k in ("box", "dfl", "cls", "kpt", "kvis", "oks_map50_95") if k in row)
        print(f"epoch {epoch + 1}: {parts} ({row['seconds']:.1f} s)", file=sys.stderr, flush=True)
        seconds.append(row["seconds"])
        if len(seconds) == 1:
            note = long_run_note(row["seconds"], cfg.epochs - epoch - 1, cfg.val_every) if cfg.time_minutes is None \
                else short_plan_note(cfg.time_minutes, row["seconds"], int(row["planned_epochs"]), cfg.epochs)
            if note:
                print(f"note: {note}", file=sys.stderr, flush=True)

    last = train(cfg, resume=args.resume, on_epoch=report, fresh=args.fresh)
    if last:
        epoch_s = statistics.median(seconds) if seconds else None
        print_table(f"omnigen train: {args.out}", ["", "value"],
                    summary_rows(last, epoch_s, time.perf_counter() - start))
    return 0


def long_run_note(epoch_seconds: float, epochs_left: int, val_every: int) -> str | None:
    """What a user is told after the first epoch when the rest of the run will take hours: how long
    an epoch took, the projection, and --time."""
    left = epoch_seconds * epochs_left
    if left < LONG_RUN_SECONDS:
        return None
    return (f"an epoch took {epoch_seconds:.0f} s: the {epochs_left} epochs left take about {left / 3600:.1f} h "
            f"(without validations, every {val_every}), then the crop stage; --time MINUTES fits the run into a "
            "budget (or fewer --epochs)")


def short_plan_note(minutes: float, epoch_seconds: float, planned: int, epochs: int) -> str | None:
    """What a user is told after the first epoch of a time-boxed run whose plan fits fewer epochs
    than --epochs: the schedule then ends sooner than the recipe's, and so do its scores."""
    if planned >= epochs:
        return None
    return (f"--time {minutes:g}: an epoch took {epoch_seconds:.0f} s, so about {planned} of the {epochs} epochs "
            "fit (planned again after every epoch): a shorter schedule than the recipe's, which scores below a "
            "whole run; a larger --time or a faster machine trains them all")


METRICS = {"oks_map50_95": "OKS mAP50:95", "ap_oks50": "AP at OKS 0.50", "precision": "precision",
           "recall": "recall", "f1": "F1", "corner_error_px": "corner error (px)",
           "corner_error_rel": "corner error rel"}
CROP = {"crop_steps": "crop stage: steps", "crop_corner_rel": "crop stage: corner error rel",
        "joint_corner_rel": "  (the stage trained with the detector)", "crop_front": "crop stage: front right",
        "crop_class_acc": "crop stage: class accuracy"}


def summary_rows(last: dict[str, Any], epoch_seconds: float | None, wall: float) -> list[tuple[str, str]]:
    """The run's summary: its epochs and one time (the run's, over its invocations: the detector's
    epochs and the crop phase; else this invocation's), the loss parts that are on (a part that is
    off is 0 throughout), the last validation where there was one (a figure nothing was matched
    for, NaN, left out), the crop phase's figures, the last learning rate readably."""
    from omnigen.detector.training.loss import PARTS  # the run's loss terms, as its rows name them

    def finite(v: Any) -> bool:
        return isinstance(v, (int, float)) and v == v and abs(v) != float("inf")

    rows: list[tuple[str, str]] = [("epochs", str(int(last["epoch"]))) if "epoch" in last else ("epochs", "-")]
    if epoch_seconds is not None:
        rows.append(("an epoch (median, s)", f"{epoch_seconds:.1f}"))
    total = float(last.get("time", wall)) + float(last.get("crop_seconds") or 0.0)
    rows.append(("time (min)", f"{total / 60:.1f}"))
    if "lr" in last:
        rows.append(("last learning rate", f"{last['lr']:.3g}"))
    rows += [(f"loss: {k}", f"{last[k]:.4f}") for k in PARTS if finite(last.get(k)) and last[k] != 0.0]
    rows += [(name, f"{last[k]:.3f}") for k, name in METRICS.items() if finite(last.get(k))]
    rows += [(name, f"{last[k]:.3f}" if isinstance(last[k], float) else str(last[k]))
             for k, name in CROP.items() if finite(last.get(k))]
    if isinstance(last.get("crop_phase"), str):
        rows.append(("crop stage", last["crop_phase"]))
    return rows
