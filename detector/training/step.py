"""One optimisation step of the detector, shared by `omnigen train` and the benchmarks.

Written so that a GPU never waits on the host inside a step: the batch is copied from pinned
memory without blocking and converted from uint8 on the device, the EMA is a fused multi-tensor
update (detector/training/ema.py), and the loss parts are summed on the device (`PartSums`) and read once
an epoch, or when the progress bar redraws, instead of a `float()` (a device synchronisation) per
part and step. For the same reason whether a step's loss was finite is a flag left on the device
(`TrainStep.finite`), collected by `FiniteWatch` and read where the loop reads the device anyway.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from omnigen.detector.training.ema import ModelEMA
from omnigen.detector.model.crop_stage import jitter_boxes, training_rois


def use_channels_last(setting: bool | None, device: torch.device) -> bool:
    """channels_last memory format: None means on for CUDA (tensor cores read NHWC without a
    transpose) and off on the CPU, where oneDNN's default layout was as fast
    (benchmarks/bench_train_speed.py step prints both)."""
    return device.type == "cuda" if setting is None else setting


def to_device(images: torch.Tensor, targets: dict[str, torch.Tensor], device: torch.device,
              channels_last: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """A loader batch on the device: images float in 0..1 (from uint8 or float), targets as they are.
    non_blocking copies overlap the previous step's kernels when the loader pinned the batch."""
    x = images.to(device, non_blocking=True)
    if not x.is_floating_point():
        x = x.float().div_(255)
    x = x.contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    return x, {k: v.to(device, non_blocking=True) for k, v in targets.items()}


class PartSums:
    """Loss parts summed over steps where they are (on the device for tensors), read once."""

    def __init__(self) -> None:
        self.sums: dict[str, torch.Tensor | float] = {}
        self.steps = 0

    def add(self, parts: dict[str, torch.Tensor | float]) -> None:
        self.steps += 1
        for k, v in parts.items():
            v = v.detach() if isinstance(v, torch.Tensor) else v
            self.sums[k] = self.sums[k] + v if k in self.sums else v

    def means(self) -> dict[str, float]:
        """Mean of each part over the steps added (one device synchronisation for all of them)."""
        keys = list(self.sums)
        tensors = [k for k in keys if isinstance(self.sums[k], torch.Tensor)]
        values = dict(zip(tensors, torch.stack([self.sums[k].float() for k in tensors]).tolist())) if tensors else {}
        n = max(1, self.steps)
        return {k: float(values.get(k, self.sums[k])) / n for k in keys}


class FiniteWatch:
    """Which steps of an epoch had a loss (or, unscaled, a gradient) that is not finite, and the
    frames of each step's batch.

    Why: one such step turns every weight into NaN, and the run would go on to save hundreds of
    NaN tensors and exit as if it had trained. A flag per step kept on the device costs the step no
    wait on the host; the trainer reads them (`first_bad`) where it reads the device anyway, and
    stops before anything of the epoch is saved, naming the first bad step's frames.
    """

    def __init__(self, steps: int, device: torch.device):
        self.flags = torch.zeros(steps, dtype=torch.bool, device=device)
        self.frames: list[list[str]] = []

    def add(self, finite: torch.Tensor, frames: list[str]) -> None:
        """Record the next step: its TrainStep.finite and the frame ids of its batch."""
        self.flags[len(self.frames)] = ~finite
        self.frames.append(frames)

    def first_bad(self) -> int | None:
        """The first recorded step (0-based) that was not finite, or None (a device synchronisation)."""
        bad = torch.nonzero(self.flags[:len(self.frames)])
        return int(bad[0, 0]) if len(bad) else None


def finite_weights(*modules: torch.nn.Module) -> bool:
    """Whether every floating tensor of the modules is finite (one reduction, one synchronisation):
    the last step of an epoch can make weights that no later loss of the epoch shows."""
    tensors = [t for m in modules for t in m.state_dict().values() if t.is_floating_point()]
    return not tensors or bool(torch.isfinite(torch.stack(torch._foreach_norm(tensors, ord=float("inf")))).all())


@dataclass
class TrainStep:
    """Forward, loss, backward, clipping, optimiser and EMA for one batch already on the device."""

    model: torch.nn.Module  # the model itself (its parameters are clipped and averaged)
    net: torch.nn.Module  # what runs the forward: the model or its DistributedDataParallel wrapper
    criterion: object  # DetectionLoss
    optimizer: torch.optim.Optimizer
    scaler: torch.amp.GradScaler
    ema: ModelEMA
    amp_dtype: torch.dtype | None
    # the last step's loss was finite, and without a gradient scaler its gradient too (a bool on the
    # device); a scaler skips the update of a non-finite gradient itself, as fp16 training expects
    finite: torch.Tensor | None = field(default=None, init=False)

    def __call__(self, images: torch.Tensor, targets: dict[str, torch.Tensor]) -> dict[str, torch.Tensor | float]:
        dtype = self.amp_dtype
        crops = None
        if getattr(self.model, "crop_net", None) is not None:  # a crop-stage model crops labelled boxes, moved
            # a stage that names classes draws its crops class-balanced (crop_stage.draw_rows)
            rows = training_rois(targets, balanced=self.model.crop_net.num_classes > 0)
            crops = (rows, targets["batch_idx"][rows], jitter_boxes(targets["bboxes"][rows].float()))
        with torch.autocast(images.device.type, dtype=dtype or torch.float32, enabled=dtype is not None):
            out = self.net(images, crops) if crops is not None else self.net(images)
        loss, parts = self.criterion(out, targets)
        finite = torch.isfinite(loss.detach())
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(loss).backward()
        self.scaler.unscale_(self.optimizer)
        norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), 10.0)
        self.finite = finite if self.scaler.is_enabled() else finite & torch.isfinite(norm)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.ema.update(self.model)
        return parts
