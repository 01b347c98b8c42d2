"""The crop stage trained apart from the detector, on clean crops of the labelled objects.

Why apart. Top-down pose estimation trains its keypoint network on crops of the labelled people,
not inside the person detector. Trained with the detector (the recipe's crop_stage.side), our
stage sees crops of augmented 320-pixel windows (zoomed, shifted, colour-jittered), shares the
detector's learning-rate schedule and EMA, and gets at most MAX_CROPS objects a step. At
prediction it crops the clean letterboxed input instead. On the same test crops, the stage of make
validate's 150-epoch detector placed corners 0.213 of sqrt(box area) from the truth about moved boxes,
where the same network trained alone for under four minutes placed them 0.189, and 0.163 after 5000
steps (docs/detector-training.md).

What it trains. A fresh stage of the detector's crop side and classes, on the train split's
objects as prediction sees them: each frame letterboxed to the detector's input size, unaugmented,
and each object cropped (`crop_stage.crop_boxes`) about `copies` boxes moved as a detector's boxes
miss the truth (`crop_stage.jitter_boxes`). The crops are cut once and kept as bytes (about 12 KiB
each at 64 px). A step draws `batch` of them, each with weight (objects of its class)^-balance, and
mirrors each with probability one half (the corners renumbered by FLIP_IDX, the heading's x negated). The loss has
the joint training's crop terms: L1 of the corners in crop units, 1 - cosine of the image heading
(times heading_gain), cross-entropy of the classes (times class_gain); and an L1 term of the
bottom face's offset from the top face (times offset_gain, `offset_loss`), the part of the corners
that tilts a lifted box most. AdamW with a one-cycle schedule.

The defaults are what was measured on make validate's data (docs/detector-training.md): the joint
training's class-balanced draws and heading gain cost the corners, so draws are uniform and the
heading's gain is a tenth of the joint one; and in one small net the class term costs the corners
too, so the stage that names classes is a SplitCropNet, its classes from a net of their own
(docs/detector-training.md, "The crop stage trained apart").

The result is the detector's checkpoint with its crop stage replaced (`attach_stage`): every other
tensor is the detector's, so `omnigen predict`, `eval` and `bev` use it as they are. A run saves
its state every `save_interval` seconds and at its end beside its output (OUT.partial, removed once
OUT is written) and a rerun with the same arguments continues from it, to the same weights as a
run never stopped.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F

from omnigen.conventions import FLIP_IDX, TURN_IDX
from omnigen.detector.model.boxes import box_area
from omnigen.detector.model.crop_stage import (MIRROR_HEADING, CropNet, SplitCropNet, crop_boxes, crop_position, from_crop_units,
                                         jitter_boxes, mirror_corners, mirror_position, outputs_of_crops, to_crop_units,
                                         training_rois)
from omnigen.detector.model.heading import heading_loss, image_heading, orient
from omnigen.detector.training.crop_train_config import CropTrainConfig


@dataclass
class CropSet:
    """Crops of labelled objects and their targets, in the crop units of the box each was cut about."""

    crops: torch.Tensor  # (N, 3, S, S) uint8
    corners: torch.Tensor  # (N, 8, 2) the true corners in crop units (to_crop_units), 0 where unlabelled
    mask: torch.Tensor  # (N, 8) bool: the corner is in front of the camera (a target)
    heading: torch.Tensor  # (N, 3) the labelled corners' image heading (heading.image_heading)
    cls: torch.Tensor  # (N,) long, the taxonomy's class ids
    boxes: torch.Tensor  # (N, 4) the box each crop was cut about, input pixels
    true_area: torch.Tensor  # (N,) the object's true 2D box area, input pixels^2
    where: torch.Tensor | None = None  # (N, 3) crop_stage.crop_position of each crop in its input

    def __len__(self) -> int:
        return len(self.cls)


def cut_crops(data, size: int, copies: int, jitter: bool, generator: torch.Generator,
              on_frame: Callable[[], None] | None = None) -> CropSet:
    """The crops of every object of `data` (a KeypointDataset without augmentation) that the joint
    training would crop (`training_rois`: a defined image heading, a side of MIN_SIDE px or more),
    `copies` of each, about its box moved at random where `jitter` (else the true box)."""
    parts: dict[str, list[torch.Tensor]] = {k: [] for k in ("crops", "corners", "mask", "heading", "cls", "boxes",
                                                           "true_area", "where")}
    for i in range(len(data)):
        s = data.sample(i)
        if on_frame is not None:
            on_frame()
        targets = {"bboxes": torch.from_numpy(s.bboxes).float(), "keypoints": torch.from_numpy(s.keypoints).float(),
                   "kpt_mask": torch.from_numpy(s.kpt_mask), "cls": torch.from_numpy(s.cls).long()}
        rows = training_rois(targets, max_crops=len(s.cls))
        if not len(rows):
            continue
        rows = rows.repeat_interleave(copies)
        true = targets["bboxes"][rows]
        boxes = jitter_boxes(true, generator) if jitter else true
        image = torch.from_numpy(s.image).permute(2, 0, 1)[None].float().div_(255)
        crops = crop_boxes(image, torch.zeros(len(rows), dtype=torch.long), boxes, size)
        kpts, mask = targets["keypoints"][rows], targets["kpt_mask"][rows].bool()
        parts["crops"].append(crops.mul_(255).round_().clamp_(0, 255).to(torch.uint8))
        parts["corners"].append(to_crop_units(kpts, boxes).nan_to_num() * mask[..., None])
        parts["mask"].append(mask)
        parts["heading"].append(image_heading(kpts, box_area(true), mask))
        parts["cls"].append(targets["cls"][rows])
        parts["boxes"].append(boxes)
        parts["true_area"].append(box_area(true))
        parts["where"].append(crop_position(boxes, torch.tensor(image.shape[2:])))
    if not parts["cls"]:
        raise ValueError(f"{data.ds.root}: no labelled object to crop in {len(data)} frames")
    return CropSet(**{k: torch.cat(v) for k, v in parts.items()})


def split_crops(dataset: str | Path, taxonomy, imgsz: int, frames: str | None, size: int, copies: int,
                generator: torch.Generator, label: str | None = None) -> CropSet:
    """`cut_crops` of the frames of split `frames` of `dataset` (None: every frame), letterboxed to
    `imgsz` and unaugmented as prediction sees them, each object cut `copies` times about moved
    boxes: what train-crop trains and scores on. With `label`, a
    progress bar of that name counts the frames."""
    from omnigen.detector.data.samples import KeypointDataset, split_frames
    from omnigen.progress import progress

    data = KeypointDataset(dataset, taxonomy, imgsz, split_frames(str(dataset), frames))
    on_frame = None
    if label is not None:
        bar = iter(progress(range(len(data)), label, total=len(data), unit="frame"))

        def on_frame() -> None:
            next(bar, None)
    return cut_crops(data, size, copies, jitter=True, generator=generator, on_frame=on_frame)


def detector_stage(state: dict[str, Any], path: str | Path = "checkpoint") -> CropNet | SplitCropNet:
    """The crop stage a detector checkpoint's `state` (of the file `path`, named in errors) was
    trained with (its model's weights)."""
    from omnigen.detector.model.checkpoint import detector_config, load_weights
    from omnigen.detector.model.network import KeypointDetector

    model = KeypointDetector(detector_config(path, state))
    load_weights(model, state["model"], path)
    if model.crop_net is None:
        raise ValueError("detector_stage: the checkpoint has no crop stage (trained with crop_stage.side=0)")
    return model.crop_net


def new_stage(size: int, num_classes: int, seed: int, split: bool = False, position: bool = False
              ) -> CropNet | SplitCropNet:
    """A freshly initialised crop stage: a CropNet, or with `split` a SplitCropNet (its classes from
    a net of their own), its corners' net told where each crop was cut where `position`
    (crop_stage.crop_position), drawn from a generator of its own seeded with `seed` (torch's
    global one is left as it was)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        if split:
            return SplitCropNet(size, num_classes, position=position)
        return CropNet(size, num_classes=num_classes, position=position)


def draw_weights(cls: torch.Tensor, balance: float) -> np.ndarray:
    """(N,) probabilities of drawing each crop: (crops of its class)^-balance, normalised."""
    _, inverse, counts = torch.unique(cls, return_inverse=True, return_counts=True)
    w = counts[inverse].double().pow(-balance).numpy()
    return w / w.sum()


def mirror_batch(x: torch.Tensor, corners: torch.Tensor, mask: torch.Tensor, heading: torch.Tensor,
                 flip: torch.Tensor, where: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The rows `flip` of a batch mirrored horizontally: crop, corners (mirror_corners), their mask
    renumbered, the heading's x negated (heading.image_heading of the mirrored corners, exactly),
    and where given, the crops' positions as in the mirrored input (mirror_position)."""
    x, corners, mask, heading = x.clone(), corners.clone(), mask.clone(), heading.clone()
    x[flip] = x[flip].flip(-1)
    corners[flip] = mirror_corners(corners[flip])
    mask[flip] = mask[flip][:, list(FLIP_IDX)]
    heading[flip] = heading[flip] * heading.new_tensor(MIRROR_HEADING)
    if where is not None:
        where = where.clone()
        where[flip] = mirror_position(where[flip])
    return x, corners, mask, heading, where


def face_offset(k: torch.Tensor) -> torch.Tensor:
    """(N, 2) the bottom face's offset from the top face of corners (N, 8, 2): the mean of corners
    4-7 less that of 0-3, what tilts a lifted box most."""
    return k[:, 4:].mean(1) - k[:, :4].mean(1)


def offset_loss(t: torch.Tensor, corners: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """L1 (x + y) of the placed `face_offset` against the labelled one (crop units), averaged over
    the objects with all eight corners labelled (0 where none is). Why: the corner term weighs the
    offset only through the eight corners' own errors."""
    full = mask.all(1)
    if not full.any():
        return t.sum() * 0.0
    return (face_offset(t[full]) - face_offset(corners[full])).abs().sum(-1).mean()


def stage_loss(net: CropNet | SplitCropNet, x: torch.Tensor, corners: torch.Tensor, mask: torch.Tensor, heading: torch.Tensor,
               cls: torch.Tensor, cfg: CropTrainConfig, where: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, dict[str, float]]:
    """The joint training's crop terms (detector/training/loss.py) on one batch, and with cfg.offset_gain the
    offset term (`offset_loss`), weighed by cfg's gains (the corners' is 1), and each term's value;
    `where`, the crops' positions, for a net that reads them."""
    h, t, logits = outputs_of_crops(net, x, where=where)
    corner = ((t - corners).abs().sum(-1) * mask).sum() / mask.sum().clamp(min=1)
    head = heading_loss(h, heading)
    parts = {"crop_corners": corner, "heading_crop": head}
    total = corner + cfg.heading_gain * head
    if cfg.offset_gain:
        parts["crop_offset"] = offset_loss(t, corners, mask)
        total = total + cfg.offset_gain * parts["crop_offset"]
    if logits is not None:
        parts["crop_cls"] = F.cross_entropy(logits, cls)
        total = total + cfg.class_gain * parts["crop_cls"]
    return total, {k: float(v.detach()) for k, v in parts.items()}


PARTIAL_FIELDS: dict[str, type | tuple[type, ...]] = {
    "config": dict, "samples": int, "identity": (dict, type(None)), "net": dict, "opt": dict, "sched": dict,
    "rng": dict, "history": list, "step": int}
"""What a partial state (train_stage's `partial`) holds, and its types."""


def read_partial(partial: Path, steps: int) -> dict[str, Any]:
    """A partial state, checked field by field: a damaged or foreign file is one line naming it
    (it is this command's own file, so the way out is to delete it)."""
    from omnigen.detector.model.checkpoint import a_kind, load_plain

    state = load_plain(partial)
    again = "delete it to start over"
    if not isinstance(state, dict):
        raise ValueError(f"{partial}: holds {a_kind(state)}, not a train-crop partial state; {again}")
    for key, kind in PARTIAL_FIELDS.items():
        if key not in state:
            raise ValueError(f"{partial}: lacks {key!r}, not a train-crop partial state; {again}")
        if not isinstance(state[key], kind) or isinstance(state[key], bool):
            raise ValueError(f"{partial}: {key} is {a_kind(state[key])}, not a train-crop partial "
                             f"state's; {again}")
    if not 0 <= state["step"] <= steps or len(state["history"]) != state["step"] \
            or not all(isinstance(row, dict) for row in state["history"]):
        raise ValueError(f"{partial}: step {state['step']} with {len(state['history'])} rows of history does not "
                         f"fit a run of {steps} steps; {again}")
    return state


def resume_partial(partial: Path, state: dict[str, Any], net: torch.nn.Module, opt: torch.optim.Optimizer,
                   sched: Any, rng: np.random.Generator) -> None:
    """Load a checked partial state into the run's net, optimiser, schedule and generator, each
    refusal one line naming the file and the field."""
    from omnigen.detector.model.checkpoint import check_tensors, load_part, load_weights

    load_weights(net, check_tensors(partial, "net", state["net"]), partial, "net")
    load_part(partial, "opt", lambda: opt.load_state_dict(state["opt"]))
    load_part(partial, "sched", lambda: sched.load_state_dict(state["sched"]))
    load_part(partial, "rng", lambda: setattr(rng.bit_generator, "state", state["rng"]))


def train_stage(data: CropSet, net: CropNet | SplitCropNet, cfg: CropTrainConfig, partial: Path | None = None,
                save_interval: float = 60.0, on_step: Callable[[int, dict[str, float]], None] | None = None,
                identity: dict[str, Any] | None = None) -> list[dict[str, float]]:
    """Train `net` on `data` for cfg.steps; the per-step loss terms. With `partial`, the state is
    saved there every `save_interval` seconds and once more at the end, and a run finding one goes
    on from it (a finished one returns at once) when it is of the same config, crops and
    `identity` (what else made the crops and the net: the caller's arguments); one of others is
    refused, naming the file. The caller removes it once the result is safely written."""
    from omnigen.detector.model.checkpoint import save_checkpoint  # torch.save to memory, then an atomic write

    rng = np.random.default_rng(cfg.seed)
    p = draw_weights(data.cls, cfg.balance)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=cfg.steps, pct_start=0.1)
    history: list[dict[str, float]] = []
    step = 0
    if partial is not None and partial.exists():
        state = read_partial(partial, cfg.steps)
        if state["config"] != asdict(cfg) or state["samples"] != len(data) or state["identity"] != identity:
            raise ValueError(f"{partial}: a partial run of other arguments ({state['config']}, "
                             f"{state['samples']} crops, {state['identity']}); delete it to start over")
        resume_partial(partial, state, net, opt, sched, rng)
        history, step = state["history"], state["step"]
    def save() -> None:
        save_checkpoint(partial, {
            "config": asdict(cfg), "samples": len(data), "identity": identity, "net": net.state_dict(),
            "opt": opt.state_dict(), "sched": sched.state_dict(), "rng": rng.bit_generator.state,
            "history": history, "step": step})

    net.train()
    last_save = time.perf_counter()
    finished_before = step >= cfg.steps
    while step < cfg.steps:
        idx = torch.from_numpy(rng.choice(len(data), cfg.batch, p=p))
        flip = torch.from_numpy(rng.random(cfg.batch) < 0.5)
        x, corners, mask, heading, where = mirror_batch(
            data.crops[idx].float().div_(255), data.corners[idx], data.mask[idx], data.heading[idx], flip,
            None if data.where is None else data.where[idx])
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=cfg.amp == "bf16"):
            loss, parts = stage_loss(net, x, corners, mask, heading, data.cls[idx], cfg, where)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        step += 1
        history.append(parts)
        if on_step is not None:
            on_step(step, parts)
        if partial is not None and step < cfg.steps and time.perf_counter() - last_save >= save_interval:
            save()
            last_save = time.perf_counter()
    if partial is not None and not finished_before:
        save()  # the finished state: scoring and writing the result may still fail
    return history


@dataclass
class StageScore:
    """A stage's corners and classes on crops of held-out objects."""

    corner_rel: float  # median distance of the labelled corners (front faced as the heading says) / sqrt(box area)
    placed_rel: float  # the same for the corners as the net placed them, not turned by its heading
    layout_rel: float  # the same with each object's 180-degree turn forgiven: the layout alone
    front: float  # share of objects whose heading points the labelled corners' way (cosine > 0)
    placed_front: float  # ... whose placed corners' own image heading does
    class_acc: float  # share of crops named their labelled class (NaN for a stage without classes)
    objects: int
    # median distance of the placed bottom face's centre from the top face's, against the labelled
    # corners' (objects with all eight labelled), / sqrt(box area): what tilts a lifted box most
    vertical_rel: float = float("nan")


def score_stage(net: CropNet | SplitCropNet, data: CropSet, batch: int = 256) -> StageScore:
    """Corners placed as prediction places them (crop_stage.refine: mirror-averaged, turned by the
    heading) on crops cut about `data.boxes`, scored against the labelled corners."""
    net.eval()
    rel, placed, layout, front, placed_front, right, vertical = [], [], [], [], [], [], []
    with torch.no_grad():
        for i in range(0, len(data), batch):
            sl = slice(i, i + batch)
            boxes = data.boxes[sl]
            where = None if data.where is None else data.where[sl]
            h, t, logits = outputs_of_crops(net, data.crops[sl].float().div_(255), mirror=True, where=where)
            true_xy = from_crop_units(data.corners[sl], boxes)
            as_placed = from_crop_units(t, boxes)
            xy = orient(as_placed, box_area(boxes), h)
            scale = data.true_area[sl].clamp(min=1e-9).sqrt()[:, None]
            m = data.mask[sl]
            d = (xy - true_xy).norm(dim=-1) / scale
            turned = (xy[:, list(TURN_IDX)] - true_xy).norm(dim=-1) / scale
            better = ((turned * m).sum(1) < (d * m).sum(1))[:, None]
            rel.append(d[m])
            full = m.all(1)
            vertical.append((face_offset(as_placed[full]) - face_offset(true_xy[full])).norm(dim=-1) / scale[full, 0])
            placed.append(((as_placed - true_xy).norm(dim=-1) / scale)[m])
            layout.append(torch.where(better, turned, d)[m])
            target = data.heading[sl]
            keep = target.norm(dim=-1) > 1e-3
            front.append(((h * target).sum(-1) > 0)[keep])
            placed_front.append(((image_heading(as_placed, box_area(boxes)) * target).sum(-1) > 0)[keep])
            if logits is not None:
                right.append(logits.argmax(-1) == data.cls[sl])
    acc = float(torch.cat(right).float().mean()) if right else float("nan")
    return StageScore(float(torch.cat(rel).median()), float(torch.cat(placed).median()),
                      float(torch.cat(layout).median()), float(torch.cat(front).float().mean()),
                      float(torch.cat(placed_front).float().mean()), acc, len(data),
                      float(torch.cat(vertical).median()) if sum(len(v) for v in vertical) else float("nan"))


def attach_stage(state: dict[str, Any], net: CropNet | SplitCropNet, size: int, record: dict[str, Any]
                 ) -> dict[str, Any]:
    """A detector checkpoint `state` with its crop stage replaced by `net`, of crops `size` px (added
    where it has none):
    the config's heading_crop, crop_classes, crop_split and crop_position set to the net's, its crop_net tensors in the model
    (the weights prediction uses) and, where the checkpoint keeps one, the raw model; `record`
    (how the stage was trained) under "crop_stage". The detector's own tensors are untouched."""
    config = dict(state["config"])
    config["heading_crop"] = size
    config["crop_classes"] = net.num_classes > 0
    config["crop_split"] = isinstance(net, SplitCropNet)
    config["crop_position"] = bool(net.position)
    from omnigen.detector.model.checkpoint import SCHEMA

    tensors = {f"crop_net.{k}": v.detach().clone() for k, v in net.state_dict().items()}
    out = dict(state)
    out["config"] = config
    for key in ("model", "raw_model"):
        if key in state:
            kept = {k: v for k, v in state[key].items() if not k.startswith("crop_net.")}
            out[key] = {**kept, **tensors}
    out["crop_stage"] = record
    out["schema"] = SCHEMA
    return out


# -- the stage's training as a whole: train-crop's and `omnigen train`'s second phase ---------------------

def cut_sets(dataset: str | Path, taxonomy, imgsz: int, train_split: str, val_split: str | None, size: int,
             copies: int, seed: int) -> dict[str, CropSet]:
    """The crops a stage trains on (`train_split`, `copies` an object) and is scored on (`val_split`,
    one each; None: every frame), cut with one generator seeded with `seed`, the training crops
    first: so train-crop and the run's crop phase cut the same crops from the same arguments."""
    gen = torch.Generator().manual_seed(seed)
    return {name: split_crops(dataset, taxonomy, imgsz, frames, size, n, gen, label=f"crop {frames}")
            for name, frames, n in (("train", train_split, copies), ("val", val_split, 1))}


PROBE_STEPS = 5
"""Steps a throwaway copy of the stage is trained to time one, when a time budget must fit the steps."""


def step_seconds(data: CropSet, net: CropNet | SplitCropNet, cfg: CropTrainConfig, steps: int = PROBE_STEPS) -> float:
    """Seconds a training step of `net` on `data` takes, timed on a throwaway copy (its first steps
    pay for the kernels' first calls: the estimate errs long, the budget's safe side). Every
    generator is left as it was."""
    import copy

    from omnigen.detector.training import time_budget

    with torch.random.fork_rng(devices=[]):
        start = time_budget.clock()
        train_stage(data, copy.deepcopy(net), replace(cfg, steps=steps))
        return (time_budget.clock() - start) / steps


def partial_steps(partial: Path) -> int | None:
    """The steps a partial state of the stage was planned for (its config), None without a readable one."""
    try:
        state = read_partial(partial, 10**9) if partial.exists() else None
    except ValueError:
        return None
    steps = state["config"].get("steps") if state else None
    return steps if isinstance(steps, int) and not isinstance(steps, bool) else None


def stage_record(call: dict[str, Any], history: list[dict[str, float]], seconds: float, score: StageScore,
                 split: str | None) -> dict[str, Any]:
    """What a checkpoint records of how its crop stage was trained ("crop_stage"): the arguments,
    the steps, the seconds, the score on the held-out crops and the last step's losses."""
    return {**call, "steps_done": len(history), "seconds": round(seconds, 1), "score": asdict(score),
            "score_split": split or "all", "last_losses": history[-1] if history else {}}


def stage_progress(steps: int, label: str) -> Callable[[int, dict[str, float]], None]:
    """An on_step for train_stage: a progress bar of `label`, and every 500 steps (and the last) a
    line of the step's losses on stderr."""
    import sys

    from omnigen.progress import progress

    bar = iter(progress(range(steps), label, total=steps, unit="step"))
    t0 = time.perf_counter()

    def report(step: int, parts: dict[str, float]) -> None:
        next(bar, None)
        if step % 500 == 0 or step == steps:
            terms = " ".join(f"{k}={v:.4f}" for k, v in parts.items())
            print(f"step {step}/{steps}: {terms} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)

    return report


def stage_config(cfg: Any) -> tuple[CropTrainConfig, bool, bool]:
    """How the run's crop phase trains its stage, from the run's TrainConfig: its crop_phase (the
    recipe's crop_stage keys), the run's seed, bf16 where the detector trains in bf16 (train-crop
    knows only off and bf16: a GPU's 'auto' is neither); and whether the stage names its classes
    with a net of their own (split) and is told where its crops were cut (position)."""
    phase = cfg.crop_phase
    own = {f.name for f in fields(CropTrainConfig)}  # the phase's keys but split and position
    stage = CropTrainConfig(**{k: v for k, v in phase.items() if k in own}, seed=cfg.seed,
                            amp="bf16" if cfg.amp == "bf16" else "off")
    return stage, bool(cfg.crop_classes and phase["split"]), bool(phase["position"])


@dataclass
class PhaseResult:
    """What the run's crop phase did: the trained stage and its record (None where it kept the
    stage trained with the detector, `why` says why), and both stages' scores on held-out crops."""

    net: CropNet | SplitCropNet | None
    record: dict[str, Any] | None
    why: str
    scores: dict[str, StageScore]


def crop_phase(cfg: Any, taxonomy, val_split: str | None, joint: CropNet | SplitCropNet | None, partial: Path,
               left: float | None, say: Callable[[str], None]) -> PhaseResult:
    """`omnigen train`'s second phase: the crop stage trained again apart from the detector on
    clean crops, as `omnigen train-crop` trains it (the same crops, net and steps from the same
    arguments), from the run's TrainConfig `cfg` (its crop_phase, crop side, classes, seed; bf16
    where the detector trained in bf16), scored on `val_split` (None: every frame). `joint` is the stage trained with the detector, scored
    beside the new one. With `left` (seconds of the run's --time budget left) the steps are those
    that fit (time_budget.fit_steps, one step timed on a throwaway copy; a partial state's own
    plan where one is there), and too few to train keep the joint stage. The state goes to
    `partial` as train_stage saves it: a killed phase goes on from it."""
    from omnigen.detector.training import time_budget

    classes = bool(cfg.crop_classes)
    stage_cfg, split, position = stage_config(cfg)
    start, budget_start = time.perf_counter(), time_budget.clock()
    sets = cut_sets(cfg.dataset, taxonomy, cfg.imgsz, cfg.train_split, val_split, cfg.heading_crop,
                    stage_cfg.copies, stage_cfg.seed)
    net = new_stage(cfg.heading_crop, len(taxonomy.classes) if classes else 0, stage_cfg.seed, split, position)
    scores = {"trained with the detector": score_stage(joint, sets["val"])} if joint is not None else {}
    if left is not None:
        planned = partial_steps(partial)
        if planned is None:
            step_s = step_seconds(sets["train"], net, stage_cfg)
            planned = time_budget.fit_steps(stage_cfg.steps, step_s, left - (time_budget.clock() - budget_start))
            if planned < stage_cfg.steps:
                say(f"the crop phase's {stage_cfg.steps} steps take {stage_cfg.steps * step_s / 60:.1f} min, "
                    f"{max(left, 0) / 60:.1f} min of --time are left: {planned} steps")
        if planned == 0:
            why = (f"too few of the crop phase's {stage_cfg.steps} steps fit in what is left of --time "
                   "(a tenth at least): the stage trained with the detector is kept")
            return PhaseResult(None, None, why, scores)
        stage_cfg = replace(stage_cfg, steps=planned)
    call = {"trained": "apart", "by": "omnigen train", "dataset": str(cfg.dataset), "train_split": cfg.train_split,
            "crop": cfg.heading_crop, "classes": classes, "split": split, "position": position, "imgsz": cfg.imgsz}
    history = train_stage(sets["train"], net, stage_cfg, partial=partial,
                          on_step=stage_progress(stage_cfg.steps, "crop stage"), identity=call)
    new = score_stage(net, sets["val"])
    scores["trained apart"] = new
    record = stage_record({**call, "config": asdict(stage_cfg)}, history, time.perf_counter() - start, new,
                          val_split)
    return PhaseResult(net, record, "", scores)
