"""Training: AdamW with cosine decay, EMA weights, validation by OKS mAP each epoch, resumable.

One process trains on the CPU or one GPU; under torchrun (WORLD_SIZE > 1) each process takes a
shard of every epoch (DistributedSampler) and DistributedDataParallel averages the gradients, with
NCCL on CUDA and gloo on the CPU. Only rank 0 validates and writes checkpoints.

What a run learns is its recipe (detector/recipe.py; TrainConfig's defaults are the validated
one), in two phases: the detector's epochs, then, where the recipe has a crop stage and steps for
it, that stage trained again apart on clean crops (crop_train.crop_phase, what `omnigen train-crop`
does) and put into best.pt and last.pt, so that `omnigen predict RUN/best.pt` uses it. A --time
budget covers both (time_budget.CROP_SHARE).

A run folder holds `last.pt` (written atomically after an epoch when `save_interval` seconds have
passed since the last write, after every validation and at the end: a kill loses at most that
much work; tiny datasets have sub-second epochs, whose every checkpoint would cost more than the
epoch), `best.pt` (the best validation OKS mAP so far), `recipe.json` (the resolved recipe, for
`--recipe`), `args.json`, `results.csv`, and while the crop phase trains its partial state.
`--resume` continues from `last.pt` with the optimiser, EMA, schedule and history, and gives the
same weights as an uninterrupted run on the CPU (each sample's augmentation is seeded from
(seed, epoch, frame), the shuffling from (seed, epoch)); a run killed in its crop phase goes on
with that phase, from its partial state.

A run folder is claimed as render claims its folders (`claim_run`, `resumed_config`): a new run
refuses a folder that holds a run's weights or results unless told `--fresh` (which deletes the
run's own files and nothing else, and refuses a folder holding anything else), and `--resume`
refuses settings other than the run's, each named ("--lr0: 0.002 there, 0.1 now"), but for where
and how fast it runs (RESUMABLE). A changed --epochs or --time is refused too: the schedule was
laid out over them, and a longer run is a new one that starts from this one's weights
(`--weights`). best.pt is written before last.pt, so a kill between the two leaves a last.pt
that the resumed run re-does; a last.pt that records its own epoch as the best while best.pt lacks
it (a kill in an older version) gets its best.pt back on resume, and a killed save's temporary
file is removed. A loss that is not finite stops the run (`FiniteWatch`): nothing of that epoch is
saved, and the error names the epoch, the step and the frames of its batch.
results.csv has a row per epoch; its `time` column is the seconds the run's epochs have taken so
far, validation included, summed over resumed invocations (the work a kill threw away is not in
it), so a run cut into time-boxed jobs still says what it cost.

`time_minutes` fits the schedule to a wall-clock budget (detector/training/time_budget.py); `weights`
starts a new run from an earlier run's weights (checkpoint.load_pretrained). Where the time of a
step goes and what was done about it: docs/detector-training.md, "Speed".
"""

from __future__ import annotations

import datetime
import json
import math
import os
import sys
import time
from contextlib import nullcontext
from dataclasses import asdict, fields, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.distributed as dist

from omnigen.detector.data.balance import describe as describe_repeat
from omnigen.detector.data.balance import check_crop_focus, check_repeat_thresh, repeat_factors
from omnigen.detector.model.checkpoint import (SCHEMA, a_kind, check_tensors, checked_fields, checkpoint_taxonomy,
                                               config_difference, detector_config, load_checkpoint, load_part,
                                               load_pretrained, load_weights, save_checkpoint)
from omnigen.detector.data.samples import Augment, KeypointDataset, split_frames
from omnigen.detector.training.ema import ModelEMA
from omnigen.detector.training.loss import DetectionLoss, LossGains
from omnigen.detector.model.network import KeypointDetector
from omnigen.detector.model.train_config import TrainConfig
from omnigen.detector.recipe import JOB as RECIPE_JOB
from omnigen.detector.recipe import NESTED, RECIPE_FILE, field_key, from_dict, recipe_json, recipe_of
from omnigen.detector.prediction.predict import EVAL_CONF, EVAL_MAX_DET, EVAL_MULTI_LABEL, PredictOptions, predict_frames
from omnigen.detector.training import time_budget
from omnigen.detector.training.time_budget import TimeBudget
from omnigen.detector.data.loader import EpochBatches, collate_uint8, loader_workers, make_loader
from omnigen.detector.training.step import FiniteWatch, PartSums, TrainStep, finite_weights, to_device, use_channels_last
from omnigen.files import TMP_PREFIX, atomic_write_bytes, atomic_write_text, dumps_json
from omnigen.outputs import json_made_by, read_prefix, same_file
from omnigen.ownership import output_lock
from omnigen.splits import TEST, split_names
from omnigen.taxonomy import load_taxonomy


def param_groups(model: torch.nn.Module, weight_decay: float) -> list[dict[str, Any]]:
    """Weight decay on conv and linear weights only; never on biases or normalisation parameters."""
    decay, no_decay = [], []
    for module in model.modules():
        for name, p in module.named_parameters(recurse=False):
            (decay if name == "weight" and not isinstance(module, torch.nn.modules.batchnorm._BatchNorm)
             else no_decay).append(p)
    return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]


OPTIMIZERS = {"adam": torch.optim.Adam, "adamw": torch.optim.AdamW}


def training_data(cfg: TrainConfig, taxonomy) -> KeypointDataset:
    """The frames of the run's training split as it trains on them: its input size, augmentation,
    windows and seed."""
    return KeypointDataset(cfg.dataset, taxonomy, cfg.imgsz, split_frames(cfg.dataset, cfg.train_split),
                           Augment(**cfg.augment), cfg.out_of_image, cfg.seed, crop=cfg.window(), crop_focus=cfg.focus())


def detection_loss(cfg: TrainConfig, model: KeypointDetector) -> DetectionLoss:
    """The run's loss: the recipe's gains on `model`'s classes."""
    return DetectionLoss(model.cfg.num_classes, gains=LossGains(kpt_l1=cfg.kpt_l1, kpt_labelled=cfg.kpt_labelled,
                                                                heading=cfg.heading_gain))


def make_optimizer(cfg: TrainConfig, model: torch.nn.Module) -> torch.optim.Optimizer:
    """Adam or AdamW with YOLO's first-moment decay 0.937, weight decay on the weights of param_groups.

    Adam adds the decay to the gradient, where its normalisation scales it like any other gradient;
    AdamW shrinks the weights directly by lr * weight_decay (Loshchilov & Hutter), the usual choice.
    """
    if cfg.optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer: {cfg.optimizer!r} is not one of {sorted(OPTIMIZERS)}")
    # fused: one kernel for all parameters on CUDA (the foreach default launches several per group)
    fused = {"fused": True} if next(model.parameters()).is_cuda else {}
    return OPTIMIZERS[cfg.optimizer](param_groups(model, cfg.weight_decay), lr=cfg.lr0, betas=(0.937, 0.999), **fused)


def learning_rate(cfg: TrainConfig, it: int, total: int) -> float:
    """Linear warm-up, then cosine decay from lr0 to lr0 * lrf over the remaining iterations: the
    last iteration (total - 1) runs at lr0 * lrf."""
    warm = min(cfg.warmup_iters, max(1, total // 5))
    if it < warm:
        return cfg.lr0 * (it + 1) / warm
    t = min(1.0, (it - warm) / max(1, total - 1 - warm))
    return cfg.lr0 * (cfg.lrf + (1 - cfg.lrf) * 0.5 * (1 + math.cos(math.pi * t)))


def kpt_sigma(cfg: TrainConfig, it: int, total: int) -> float:
    """Sigma of the keypoint loss at iteration `it`: geometric from kpt_sigma_start to kpt_sigma_end.

    The design's kernel exp(-d / (2 sigma^2 a)) with sigma = 0.125 is so narrow that a corner
    predicted where a fresh head puts it (at the anchor, about 0.7 sqrt(a) away) gets a gradient
    scaled by exp(-16): far corners would never move. A wider sigma early gives them a slope; from
    kpt_sigma_anneal of the run on, the loss is the design's formula with sigma = kpt_sigma_end.
    The design's end is 0.125. pycocotools' OKS, which `omnigen eval` reports, reads
    the same sigma as exp(-d / (8 sigma^2 a)): the loss's kernel with sigma 0.25 (what
    Ultralytics' keypoint loss uses), twice as wide as the design's in distance. End there
    (schedule.kpt_sigma_end=0.25, the recipe's) to train on the metric's own kernel.
    """
    end = cfg.kpt_sigma_anneal * total
    if it >= end or cfg.kpt_sigma_start <= cfg.kpt_sigma_end:
        return cfg.kpt_sigma_end
    return cfg.kpt_sigma_start * (cfg.kpt_sigma_end / cfg.kpt_sigma_start) ** (it / end)


AMP_MODES = ("auto", "bf16", "fp16", "off")


def fast_bf16(device: torch.device) -> bool:
    """Whether `device` runs bfloat16 convolutions natively (CUDA Ampere and later; CPUs with
    AVX512-BF16 or AMX). Elsewhere bf16 is emulated and slower than float32."""
    if device.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    if device.type == "cpu":
        return any(getattr(torch.cpu, probe, lambda: False)()
                   for probe in ("_is_avx512_bf16_supported", "_is_amx_tile_supported"))
    return False


def autocast_dtype(amp: str, device: torch.device) -> torch.dtype | None:
    """The autocast dtype of the forward pass, or None for float32.

    'auto' is fp16 on CUDA (with a gradient scaler, as Ultralytics trains) and float32 on the CPU.
    bf16 is a choice, not the CPU default: on a 2-core CPU with AVX512-BF16 a step of the nano P2
    model at batch 16 and 320 px takes about 0.65 of a float32 one, but bf16 keeps 8 bits of
    mantissa, and the four-frame overfit run ends well short of float32's fit
    (benchmarks/bench_train_speed.py step --overfit prints both). For runs far from that precision (any
    run short of convergence) the speed is worth it. The loss always runs in float32
    (DetectionLoss casts the head's outputs).
    """
    if amp not in AMP_MODES:
        raise ValueError(f"TrainConfig.amp: {amp!r} is not one of {', '.join(AMP_MODES)}")
    if amp == "auto":
        return torch.float16 if device.type == "cuda" else None
    if amp == "off":
        return None
    if amp == "fp16":
        if device.type != "cuda":
            raise ValueError(f"TrainConfig.amp: fp16 needs a CUDA device, this run trains on {device}")
        return torch.float16
    if not fast_bf16(device):
        print(f"warning: --amp bf16 on {device}, which emulates bfloat16: slower than float32",
              file=sys.stderr)
    return torch.bfloat16


def check_sizes(cfg: TrainConfig) -> None:
    """The input and the crop window must be multiples of the largest stride (the feature maps of
    the levels must line up in the neck; a window as large as the input or larger is whole images,
    TrainConfig.window), the crop stage's side one of 16 (0: none). Each named by its recipe key."""
    stride = 64 if cfg.p6 else 32
    for name, step in (("imgsz", stride), ("crop", stride), ("heading_crop", 16)):  # the crop net halves it 4 times
        value = getattr(cfg, name)
        if value is not None and (value < 0 or value % step or (value == 0 and name != "heading_crop")):
            raise ValueError(f"TrainConfig.{name} ({field_key(name)}): {value} is not a positive multiple of {step}")


def check_sampling(cfg: TrainConfig) -> None:
    """Class-balanced sampling's settings (balance's checks), refused before any data is read. The
    focus share is checked as a probability whether or not there are windows to centre."""
    try:
        check_crop_focus(cfg.crop_focus, cfg.window() or cfg.imgsz)
        check_repeat_thresh(cfg.repeat_thresh)
    except ValueError as e:
        raise ValueError(f"TrainConfig.{e}") from None


def frame_repeats(cfg: TrainConfig, data: KeypointDataset) -> np.ndarray | None:
    """Each training frame's repeat factor (balance.repeat_factors), None without --repeat-thresh;
    also what bench_learning counts an epoch's frames by."""
    return repeat_factors(data.frame_classes(), len(data.taxonomy.classes), cfg.repeat_thresh) \
        if cfg.repeat_thresh > 0 else None


def resolve_val_split(root: str, name: str | None) -> str | None:
    if name is not None:
        return name
    names = split_names(root)
    return "val" if "val" in names else TEST if TEST in names else None


def distributed() -> tuple[int, int, int]:
    """(rank, local rank, world size) from torchrun's environment; (0, 0, 1) otherwise."""
    return int(os.environ.get("RANK", 0)), int(os.environ.get("LOCAL_RANK", 0)), int(os.environ.get("WORLD_SIZE", 1))


def pick_device(cfg: TrainConfig, local_rank: int) -> torch.device:
    if cfg.device:
        return torch.device(cfg.device)
    return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")


def validate(model: KeypointDetector, data: KeypointDataset, split: str | None, batch: int) -> dict[str, float]:
    """OKS mAP of the model on a split (omnigen eval's numbers, overall row; adherence left to eval)."""
    from omnigen.detector.evaluation.oks_eval import evaluate

    # the network's own corners (vertical="off"): the snap to the image's vanishing point is a step after
    # it (omnigen predict, eval) that would cost a line segment detection an image at every validation
    preds = predict_frames(model, data, PredictOptions(imgsz=data.size, conf=EVAL_CONF, batch=batch, max_det=EVAL_MAX_DET,
                                                       multi_label=EVAL_MULTI_LABEL, vertical="off"))
    row = evaluate(data.ds, preds, split=split, taxonomy=data.taxonomy, adherence=False, sizes=False).row("overall")
    return {"oks_map50_95": row.oks_map50_95, "ap_oks50": row.ap_oks50, "precision": row.precision,
            "recall": row.recall, "f1": row.f1, "corner_error_px": row.corner_error_px,
            "corner_error_rel": row.corner_error_rel}


CROP_PARTIAL = "crop-phase.partial.pt"
"""The crop phase's state while it trains (crop_train.train_stage's partial), removed at its end."""
RUN_FILES = ("last.pt", "best.pt", "results.csv", "args.json", RECIPE_FILE, CROP_PARTIAL)
"""What `omnigen train` writes into its run folder, besides its temporary files."""

RESUMABLE = ("out", "device", "workers", "cache")
"""The settings a resumed run may change: where the folder and the run are, its loader processes
and its image cache; they give the same weights. Every other one is the run's."""

FLAGS = {"dataset": "DATASET", "time_minutes": "--time", "epochs": "--epochs", "val_every": "--val-every",
         "seed": "--seed", "amp": "--amp", "channels_last": "--channels-last", "weights": "--weights",
         "train_split": "--train-split", "val_split": "--val-split"}
"""How the run's settings are named to a user: their flags. Recipe fields are named by their key
(recipe.field_key: 'optim.lr0'), the rest (the tests' fields) as TrainConfig's."""


def flag_of(name: str) -> str:
    """How a TrainConfig field is named to a user: its flag, its recipe key, else the field."""
    return FLAGS.get(name) or field_key(name) or f"TrainConfig.{name}"


def differences(name: str, was: Any, now: Any) -> list[str]:
    """'KEY: X there, Y now' for each part of a setting that differs: a dict (augment, crop_phase,
    predict: recipe.NESTED) key by key, named by its recipe key."""
    section = next((s for s, kept in NESTED.items() if kept == name), None)
    if section and isinstance(was, dict) and isinstance(now, dict):
        return [f"{section}.{k}: {_shown(was.get(k))} there, {_shown(now.get(k))} now"
                for k in dict.fromkeys([*was, *now]) if was.get(k) != now.get(k)]
    return [f"{flag_of(name)}: {_shown(was)} there, {_shown(now)} now"]


def _shown(value: Any) -> str:
    return "unset" if value is None else str(value)


def _same_setting(name: str, was: Any, now: Any) -> bool:
    if was == now:
        return True
    # the same dataset folder however it is spelled (relative, through a link)
    return name == "dataset" and os.path.exists(was) and os.path.exists(now) and os.path.samefile(was, now)


def is_run_file(path: Path) -> bool:
    """Whether `path`, named as one of RUN_FILES, is what `omnigen train` writes there (by its first
    bytes: a torch archive, results.csv's header, a JSON object of TrainConfig fields, a recipe file
    marked as train's): all that --fresh deletes."""
    head = read_prefix(path)
    if path.suffix == ".pt":
        return head.startswith(b"PK\x03\x04") and b"/data.pkl" in head[:200]
    if path.name == "results.csv":
        return head.startswith(b"epoch,")
    if path.name == RECIPE_FILE:
        return json_made_by(RECIPE_JOB)(path)
    try:
        recorded = json.loads(head)
    except ValueError:
        return False
    return isinstance(recorded, dict) and {"dataset", "out", "epochs", "imgsz"} <= set(recorded)


def claim_run(out: Path, fresh: bool, weights: str | None = None) -> None:
    """Check that `out` may be the folder of a new run, before anything is read or written; with
    `fresh`, that its run may be deleted (`delete_run`, called once the run's inputs have loaded,
    so that a run refused for a missing dataset or a bad --weights deletes nothing).

    A folder holding a run's weights or results (last.pt, best.pt, results.csv) is refused: a new
    run would replace them. `fresh` may delete them only from a folder that holds nothing but a
    run's own files, each recognised as train's (is_run_file), and whose args.json says it is
    omnigen train's run: a .pt is any torch archive, so without that an Ultralytics weights/ folder
    (best.pt, last.pt) would pass. --weights may not name a file --fresh would delete. Files of
    others beside no run are left alone (benchmarks/validate.py keeps its markers in the run
    folder); an args.json or recipe.json not written by train is refused, as it would be overwritten.
    """
    if not out.is_dir():
        return
    for name in ("args.json", RECIPE_FILE):
        if (out / name).exists() and not is_run_file(out / name):
            raise ValueError(f"{out / name}: was not written by 'omnigen train'; refusing to overwrite it "
                             "(choose another --out)")
    held = [name for name in RUN_FILES[:3] if (out / name).exists()]
    ours = (out / "args.json").is_file() and is_run_file(out / "args.json")
    if held and not ours:
        raise ValueError(f"{out}: holds {', '.join(held)} but no args.json of 'omnigen train'; it is not a run this "
                         "command made, and nothing in it is replaced or deleted: choose another --out")
    if held and not fresh:
        raise ValueError(f"{out}: holds a training run ({', '.join(held)}); add --resume to continue it, --fresh "
                         "to delete its files and start over, or choose another --out")
    if fresh and weights and any(same_file(weights, out / name) for name in RUN_FILES):
        raise ValueError(f"--weights {weights}: is a file of the run in {out}, which --fresh deletes; copy it "
                         "elsewhere first, or train into another --out")
    if not fresh:
        return
    theirs = sorted(p.name for p in out.iterdir()
                    if not (p.name in RUN_FILES and is_run_file(p)) and not p.name.startswith(TMP_PREFIX))
    if theirs:
        more = f" and {len(theirs) - 5} more" if len(theirs) > 5 else ""
        raise ValueError(f"{out}: --fresh deletes only a run's own files ({', '.join(RUN_FILES)}), and this folder "
                         f"also holds {', '.join(theirs[:5])}{more}, which 'omnigen train' did not make; choose "
                         "another --out")


def delete_run(out: Path) -> None:
    """--fresh's deletion of the run's own files (claim_run checked them), last.pt first: a kill
    midway leaves no run that --resume would take up."""
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)


RESUME_FIELDS = {"train_config": dict, "raw_model": dict, "optimizer": dict, "ema_updates": int, "epoch": int,
                 "best_fitness": (int, float), "history": list}
"""What --resume reads from last.pt beside what prediction reads, and its types."""


def resumed_config(cfg: TrainConfig, state: dict[str, Any], path: Path) -> TrainConfig:
    """The run's recorded settings (last.pt's train_config) with this invocation's RESUMABLE ones.

    Any other setting given differently is refused, every difference named, as render refuses a
    folder of other frames: a resume that silently took the run's --lr0 or dataset over the one
    given would train something other than what was asked for.
    """
    for key, kind in RESUME_FIELDS.items():
        if key not in state:
            raise ValueError(f"{path}: lacks {key!r}, which --resume needs (not a checkpoint of omnigen train)")
        if not isinstance(state[key], kind) or isinstance(state[key], bool):
            raise ValueError(f"{path}: {key} is {a_kind(state[key])}, not what --resume needs")
    if not all(isinstance(row, dict) for row in state["history"]):
        raise ValueError(f"{path}: history holds something other than rows of numbers")
    check_tensors(path, "raw_model", state["raw_model"])
    # a checkpoint of schema 1 was read with the fields it lacks filled in (checkpoint.upgraded)
    recorded = checked_fields(path, "train_config", state["train_config"], TrainConfig)
    checked_fields(path, "train_config.augment", recorded.augment, Augment)
    # train_config.predict was checked as the checkpoint loaded (checkpoint.check_state), for every reader
    from_dict({"crop_stage": recorded.crop_phase}, f"{path}: train_config.crop_phase")
    differ = [f.name for f in fields(TrainConfig) if f.name not in RESUMABLE
              and not _same_setting(f.name, getattr(recorded, f.name), getattr(cfg, f.name))]
    if differ:
        said = "; ".join(d for k in differ for d in differences(k, getattr(recorded, k), getattr(cfg, k)))
        raise ValueError(f"{cfg.out}: was trained with other settings ({said}; recorded in {path}); --resume goes on "
                         "with the run's own (only --device, --workers and --cache may change): give its settings "
                         f"(its recipe is {Path(cfg.out) / RECIPE_FILE}: --recipe), or train a new run into another "
                         "--out (--weights starts one from its weights)")
    return replace(recorded, **{k: getattr(cfg, k) for k in RESUMABLE})


def tidy_run(out: Path, state: dict[str, Any] | None) -> None:
    """Undo what a kill left in a run folder before the run goes on in it: the temporary file of a
    save cut short, and where last.pt records its own epoch as the run's best while best.pt does
    not hold it (killed between the two writes, before best.pt was written first), best.pt."""
    for tmp in out.glob(TMP_PREFIX + "*"):
        if tmp.is_file():
            tmp.unlink(missing_ok=True)
    if state is None or not state["history"]:
        return
    own = state["history"][-1].get("oks_map50_95") if isinstance(state["history"][-1], dict) else None
    if own is None or own != state["best_fitness"]:
        return
    best = out / "best.pt"
    try:
        kept = load_checkpoint(best).get("best_fitness", -1.0) if best.exists() else -1.0
    except ValueError:
        kept = -1.0  # a damaged best.pt: the run's own file, replaced
    if not isinstance(kept, (int, float)) or kept < own:
        atomic_write_bytes(best, (out / "last.pt").read_bytes())


def train(cfg: TrainConfig, resume: bool = False, on_epoch: Callable[[int, dict[str, float]], None] | None = None,
          stop_after: int | None = None, fresh: bool = False) -> dict[str, Any]:
    """Run (or resume) training; returns the final history row of rank 0.

    `stop_after` ends the run after that many epochs in total (the schedule still spans
    cfg.epochs), as a kill would, so that a later `resume=True` continues it: time-boxed jobs on a
    cluster do the same. `fresh` deletes a run already in cfg.out first (claim_run). Rank 0 holds
    the folder's lock (omnigen.ownership.output_lock) for the whole run: two runs into one folder
    would overwrite each other's checkpoints.
    """
    if resume and fresh:
        raise ValueError("--resume continues the run in --out and --fresh deletes it; give one of them")
    with output_lock(cfg.out, "train") if distributed()[0] == 0 else nullcontext():
        return _train(cfg, resume, fresh, on_epoch, stop_after)


def _train(cfg: TrainConfig, resume: bool, fresh: bool, on_epoch: Callable[[int, dict[str, float]], None] | None,
           stop_after: int | None) -> dict[str, Any]:
    """train() inside the run folder's lock."""
    clock = time_budget.clock  # seconds of the run's epochs and budget (tests may replace it)
    entered = clock()  # a time budget counts the setup (dataset, image cache) too
    check_sizes(cfg)  # before the folder is claimed: a refused run deletes nothing (--fresh)
    check_sampling(cfg)
    rank, local_rank, world = distributed()
    device = pick_device(cfg, local_rank)
    if world > 1 and not dist.is_initialized():
        if device.type == "cuda":
            torch.cuda.set_device(device)  # NCCL collectives use the current device: one GPU per process
        # rank 0 validates while the others wait at the epoch's barrier: allow long validations
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", timeout=datetime.timedelta(hours=2))
    out = Path(cfg.out)
    state = load_checkpoint(out / "last.pt") if resume else None
    if state is not None:
        cfg = resumed_config(cfg, state, out / "last.pt")
        taxonomy = checkpoint_taxonomy(state)
    else:
        claim_run(out, fresh, cfg.weights)
        taxonomy = load_taxonomy(cfg.taxonomy)
    if rank == 0 and (resume or fresh or (out / "args.json").exists()):
        tidy_run(out, state)
    if state is not None and run_finished(cfg, state):  # its crop phase too: last.pt is the run's result
        return {**state["history"][-1], **phase_summary(state.get("crop_stage"), state.get("crop_phase"))} \
            if state["history"] else {}
    torch.manual_seed(cfg.seed)

    val_name = resolve_val_split(cfg.dataset, cfg.val_split)
    data = training_data(cfg, taxonomy)
    if len(data) == 0:
        raise ValueError(f"{cfg.dataset}: split {cfg.train_split!r} has no frames")
    val = KeypointDataset(cfg.dataset, taxonomy, cfg.imgsz, split_frames(cfg.dataset, val_name))
    if cfg.cache:  # before the loader forks its workers, which then share it
        data.cache_images(show_progress=rank == 0)
        if rank == 0:  # only rank 0 validates
            val.cache_images(show_progress=True)

    model = KeypointDetector(cfg.model_config(len(taxonomy.classes)))
    if state is None and cfg.weights:  # a new run from earlier weights: fresh optimiser, epoch 0
        for note in load_pretrained(model, cfg.weights, taxonomy):
            if rank == 0:
                print(f"note: {note}", file=sys.stderr, flush=True)
    channels_last = use_channels_last(cfg.channels_last, device)
    model = model.to(device, memory_format=torch.channels_last if channels_last else torch.preserve_format)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True  # fixed input sizes: each convolution's kernel is timed once
    ema = ModelEMA(model, cfg.ema_decay, cfg.ema_tau)  # after the move: it pairs the model's tensors
    optimizer = make_optimizer(cfg, model)
    start_epoch, best, history = 0, -1.0, []
    if state is not None:
        path = out / "last.pt"
        config_difference(path, detector_config(path, state), model.cfg)
        load_weights(model, state["raw_model"], path, "raw_model")
        load_weights(ema.ema, state["model"], path, "model")
        ema.updates = int(state["ema_updates"])
        load_part(path, "optimizer", lambda: optimizer.load_state_dict(state["optimizer"]))
        start_epoch, best, history = int(state["epoch"]) + 1, float(state["best_fitness"]), list(state["history"])
    criterion = detection_loss(cfg, model)
    amp_dtype = autocast_dtype(cfg.amp, device)
    # fp16 gradients underflow without scaling; bf16 has float32's range and needs none
    scaler = torch.amp.GradScaler(device.type, enabled=amp_dtype == torch.float16)
    if state is not None and state.get("scaler"):
        load_part(out / "last.pt", "scaler", lambda: scaler.load_state_dict(state["scaler"]))
    ddp = torch.nn.parallel.DistributedDataParallel(model, device_ids=[local_rank] if device.type == "cuda" else None) \
        if world > 1 else model
    step = TrainStep(model, ddp, criterion, optimizer, scaler, ema, amp_dtype)

    shard = torch.utils.data.distributed.DistributedSampler(data, world, rank, shuffle=True, seed=cfg.seed) \
        if world > 1 else None
    per_step = max(1, cfg.batch // world)
    repeat = frame_repeats(cfg, data)
    if repeat is not None and rank == 0:
        print(f"note: {describe_repeat(repeat)}", file=sys.stderr, flush=True)
    sampler = EpochBatches(len(data), per_step, cfg.seed, start_epoch, shard, repeat)
    batches = iter(make_loader(data, sampler, loader_workers(cfg.workers, device), pin=device.type == "cuda",
                               collate_fn=collate_uint8))
    if rank == 0:
        if fresh and state is None:  # now that the dataset, the sizes and --weights have loaded
            delete_run(out)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / "args.json", dumps_json(asdict(cfg)))
        atomic_write_text(out / RECIPE_FILE, recipe_json(recipe_of(asdict(cfg))))
    iters_per_epoch = sampler.per_epoch()
    from tqdm import tqdm

    budget = TimeBudget(time_budget.detector_seconds(cfg.time_minutes, crop_phase_due(cfg)), cfg.epochs) \
        if cfg.time_minutes is not None else None
    end = cfg.epochs  # the run's last epoch (exclusive): with a time budget, planned as it goes
    validates = len(val) > 0 and cfg.val_every > 0  # val_every 0: never (a benchmark scores on its own)
    last_validated = max((int(r["epoch"]) for r in history if "oks_map50_95" in r), default=0)
    last_save, started = time.perf_counter(), clock()
    time_before = float(history[-1].get("time", 0.0)) if history else 0.0  # the resumed invocations' share

    def used() -> float:  # seconds of the budget spent: earlier invocations' epochs, all of this one
        return time_before + clock() - entered

    if budget is not None and history:  # resumed: plan from the epochs the earlier invocations measured
        budget.epoch_seconds = [float(r["seconds"]) for r in history[-4:]]
        budget.val_seconds = next((float(r["val_seconds"]) for r in reversed(history) if "val_seconds" in r), None)
        # the plan the checkpoint's epoch made for the next (the uninterrupted run's), else one now
        end = agree(int(state.get("planned_epochs") or budget.plan(start_epoch, used(), cfg.val_every, validates)),
                    device, world)

    frame_ids = data.ds.frame_ids
    saved = start_epoch if state is not None else None  # the epochs last.pt holds
    epoch = start_epoch
    while epoch < (end if stop_after is None else min(end, stop_after)):
        total = end * iters_per_epoch
        model.train()
        sums = PartSums()
        watch = FiniteWatch(iters_per_epoch, device)
        bar = tqdm(range(iters_per_epoch), desc=f"epoch {epoch + 1}/{end}", disable=rank != 0, leave=False,
                   dynamic_ncols=True, mininterval=0.5 if sys.stderr.isatty() else 60.0)  # logs: a line a minute
        t0, show = clock(), time.perf_counter()
        for i in bar:
            images, targets, samples = next(batches)  # this epoch's i-th batch: the sampler goes epoch by epoch
            it = epoch * iters_per_epoch + i
            for g in optimizer.param_groups:
                g["lr"] = learning_rate(cfg, it, total)
            criterion.kpt_sigma = kpt_sigma(cfg, it, total)
            criterion.turn_free = it >= cfg.kpt_turn_start * total
            sums.add(step(*to_device(images, targets, device, channels_last)))
            watch.add(step.finite, [frame_ids[s.frame_index] for s in samples])
            if rank == 0 and time.perf_counter() >= show:  # read the device's sums only when the bar may redraw
                if world == 1:  # one process stops at once; several stop together at the epoch's end
                    stop_if_not_finite(watch, epoch, out, saved, device, world)
                # refresh=False: a redraw per step would defeat the log's one line a minute
                bar.set_postfix({k: f"{v:.3f}" for k, v in sums.means().items()}, refresh=False)
                show = time.perf_counter() + bar.mininterval
        means = sums.means()  # waits for the epoch's last step
        stop_if_not_finite(watch, epoch, out, saved, device, world, model, ema.ema)
        row: dict[str, float] = {"epoch": epoch + 1, "lr": optimizer.param_groups[0]["lr"],
                                 "seconds": clock() - t0}
        row.update(means)
        if budget is not None:
            # The one decision of the epoch, before its validation: whether it is the last, and else
            # the plan of the epochs after it (their schedule). Nothing later (validation, save, a
            # slow disk) changes it, so an epoch that ends the run is always validated and saved.
            budget.epoch_seconds.append(row["seconds"])
            if epoch + 1 < end:  # a planned last epoch stays the last: its schedule has ended
                end = agree(budget.plan(epoch + 1, used(), cfg.val_every, validates), device, world)
        if rank == 0:
            validated = validates and (epoch + 1 == end or (
                (epoch + 1) % cfg.val_every == 0 if budget is None
                else epoch + 1 - last_validated >= budget.val_cadence(cfg.val_every)))
            if validated:
                t_val = clock()
                row.update(validate(ema.ema, val, val_name if val_name != 'all' else None, per_step))
                row["val_seconds"] = clock() - t_val
                last_validated = epoch + 1
                if budget is not None:
                    budget.val_seconds = row["val_seconds"]
            row["time"] = time_before + clock() - started
            history.append(row)
            fitness = row.get("oks_map50_95", -1.0)
            last = epoch + 1 == end or epoch + 1 == stop_after
            due = validated or last or time.perf_counter() - last_save >= cfg.save_interval
            if on_epoch is not None:  # with the plan after this epoch (history's rows keep results.csv's columns)
                on_epoch(epoch, {**row, "planned_epochs": end})
            if due:
                last_save = time.perf_counter()
                ckpt = {"schema": SCHEMA, "config": model.cfg.to_dict(), "classes": taxonomy.classes,
                        "taxonomy": taxonomy.to_dict(),
                        "model": ema.ema.state_dict(), "raw_model": model.state_dict(), "ema_updates": ema.updates,
                        "optimizer": optimizer.state_dict(), "scaler": scaler.state_dict(),
                        "epoch": epoch, "best_fitness": max(best, fitness), "planned_epochs": end,
                        "history": history, "train_config": asdict(cfg)}
                if fitness > best:  # before last.pt: a kill between the two leaves a last.pt that re-does this epoch
                    best = fitness
                    save_checkpoint(out / "best.pt", ckpt)
                save_checkpoint(out / "last.pt", ckpt)
                saved = epoch + 1
                write_results_csv(out / "results.csv", history)
        if world > 1:
            dist.barrier(device_ids=[torch.cuda.current_device()] if device.type == "cuda" else None)
        epoch += 1
    final = history[-1] if history else {}
    if rank == 0 and epoch == end and crop_phase_due(cfg):  # the detector's schedule ended: the second phase
        left = cfg.time_minutes * 60 - used() if cfg.time_minutes is not None else None
        final = {**final, **run_crop_phase(cfg, taxonomy, val_name, ema.ema.crop_net, out, left)}
    return final


def crop_phase_due(cfg: TrainConfig) -> bool:
    """Whether the run has a second phase: a crop stage, and steps to train it apart."""
    return cfg.heading_crop > 0 and int(cfg.crop_phase.get("steps", 0)) > 0


def run_finished(cfg: TrainConfig, state: dict[str, Any]) -> bool:
    """Whether last.pt's `state` ends the run: the detector's planned epochs done, and its crop
    phase where it has one (its mark, "crop_phase", is written into last.pt last)."""
    detector_done = int(state["epoch"]) + 1 >= int(state.get("planned_epochs") or cfg.epochs)
    return detector_done and (not crop_phase_due(cfg) or isinstance(state.get("crop_phase"), str))


def run_crop_phase(cfg: TrainConfig, taxonomy: Any, val_name: str | None, joint: torch.nn.Module | None, out: Path,
                   left: float | None) -> dict[str, Any]:
    """The run's second phase (crop_train.crop_phase: the crop stage trained again apart, within
    `left` seconds of the --time budget where there is one), its stage put into best.pt and then
    last.pt (crop_train.attach_stage; the detector's tensors untouched), each marked "crop_phase":
    last.pt last, so a kill before leaves a run whose --resume does the phase again, from its
    partial state. Returns the phase's figures for the summary."""
    import copy

    from omnigen.detector.training.crop_train import attach_stage, crop_phase

    def say(text: str) -> None:
        print(f"note: {text}", file=sys.stderr, flush=True)

    if joint is not None:  # scored on the CPU beside the new stage, as prediction's weights hold it
        joint = copy.deepcopy(joint).to("cpu", memory_format=torch.contiguous_format).float()
    result = crop_phase(cfg, taxonomy, val_name, joint, out / CROP_PARTIAL, left, say)
    if result.net is None:
        say(result.why)
    for name in ("best.pt", "last.pt"):
        if (out / name).exists():
            state = load_checkpoint(out / name)
            if result.net is not None:
                state = attach_stage(state, result.net, cfg.heading_crop, result.record)
            state["crop_phase"] = result.why or "trained"
            save_checkpoint(out / name, state)
    (out / CROP_PARTIAL).unlink(missing_ok=True)
    return phase_summary(result.record, result.why, result.scores.get("trained with the detector"))


def phase_summary(record: dict[str, Any] | None, why: str | None, joint: Any = None) -> dict[str, Any]:
    """The crop phase's figures for the run's summary: its steps, seconds and score on held-out
    crops (and the stage trained with the detector's), or why it kept that stage."""
    if not isinstance(record, dict):
        return {"crop_phase": why} if why else {}
    score = record.get("score") or {}
    out = {"crop_steps": record.get("steps_done"), "crop_seconds": record.get("seconds"),
           "crop_corner_rel": score.get("corner_rel"), "crop_front": score.get("front"),
           "crop_class_acc": score.get("class_acc")}
    if joint is not None:
        out["joint_corner_rel"] = joint.corner_rel
    return out


class NonFiniteLoss(RuntimeError):
    """Training reached a loss (or weights) that is not finite; nothing of that epoch was saved."""


def stop_if_not_finite(watch: FiniteWatch, epoch: int, out: Path, saved: int | None, device: torch.device,
                       world: int, *modules: torch.nn.Module) -> None:
    """Raise NonFiniteLoss, naming the epoch, the step and the frames of its batch, when a step of
    this epoch so far was not finite or (given `modules`, at the epoch's end) its weights are not.
    Every process calls it at the epoch's end: they stop together."""
    bad = watch.first_bad()
    if bad is None and modules and not finite_weights(*modules):
        bad = len(watch.frames) - 1  # the epoch's last update made them: no loss of the epoch showed it
    if not any_rank(bad is not None, device, world):
        return
    kept = f"{out / 'last.pt'} holds epoch {saved}, the last saved" if saved else "nothing was saved"
    if bad is None:
        raise NonFiniteLoss(f"{out}: training stopped at epoch {epoch + 1}: another process's loss was not finite; "
                            f"{kept}")
    frames = watch.frames[bad]
    named = ", ".join(frames[:16]) + (f" and {len(frames) - 16} more" if len(frames) > 16 else "")
    raise NonFiniteLoss(f"{out}: training stopped: the loss was not finite at epoch {epoch + 1}, step {bad + 1} of "
                        f"{len(watch.flags)} (frames {named}); nothing of this epoch was saved, {kept}; check those "
                        "frames' labels, or train with a lower --lr0")


def any_rank(flag: bool, device: torch.device, world: int) -> bool:
    """Whether `flag` holds on any process."""
    if world == 1:
        return flag
    t = torch.tensor([int(flag)], device=device if device.type == "cuda" else "cpu")
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item())


def agree(value: int, device: torch.device, world: int) -> int:
    """Rank 0's value on every process: the ranks time their epochs apart, and must end together."""
    if world == 1:
        return value
    t = torch.tensor([value], device=device if device.type == "cuda" else "cpu")
    dist.broadcast(t, 0)
    return int(t.item())


def write_results_csv(path: Path, history: list[dict[str, float]]) -> None:
    keys = list(dict.fromkeys(k for row in history for k in row))
    lines = [",".join(keys)] + [",".join(f"{row.get(k, float('nan')):.6g}" for k in keys) for row in history]
    atomic_write_text(path, "\n".join(lines) + "\n")

