"""One optimisation step of the detector, shared by `omnigen train` and the benchmarks.

Written so that a GPU never waits on the host inside a step: the batch is copied from pinned
memory without blocking and converted from uint8 on the device, the EMA is a fused multi-tensor
update (detector/ema.py), and the loss parts are summed on the device (`PartSums`) and read once
an epoch, or when the progress bar redraws, instead of a `float()` (a device synchronisation) per
part and step.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from omnigen.detector.ema import ModelEMA
from omnigen.detector.crop_stage import jitter_boxes, training_rois


def use_channels_last(setting: bool | None, device: torch.device) -> bool:
    """channels_last memory format: None means on for CUDA (tensor cores read NHWC without a
    transpose) and off on the CPU, where oneDNN's default layout was as fast
    (benchmarks/bench_train_step.py prints both)."""
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
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(loss).backward()
        self.scaler.unscale_(self.optimizer)
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), 10.0)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.ema.update(self.model)
        return parts
