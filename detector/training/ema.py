"""Exponential moving average of a model's weights: the model that training validates and saves.

The update runs every step, so it is written for an accelerator: the pairs of (EMA, model) tensors
are collected once, and a step is two fused multi-tensor kernels (torch._foreach_mul_ and
_foreach_add_) over the floating ones plus one _foreach_copy_ of the integer buffers
(BatchNorm's batch counters). Building the pairs from `state_dict()` every step, as before, cost
about 18 ms a step on an H200 (two dict walks of a few hundred tensors and a kernel each).
"""

from __future__ import annotations

import copy
import math

import torch


def _tensors(module: torch.nn.Module) -> list[tuple[str, torch.Tensor]]:
    """Parameters and buffers by name, in state_dict order (the objects themselves, not copies)."""
    return list(module.named_parameters()) + list(module.named_buffers())


class ModelEMA:
    """EMA weights (and buffers): ema = d * ema + (1 - d) * model, d ramped up by `tau` updates.

    The tensor pairs are taken at construction: build it after the model has its final device and
    memory format (Module.to swaps the buffers for new tensors). load_state_dict on either model
    copies in place and keeps the pairs valid. The EMA therefore follows that one model, its
    `source`, for good: `update` refuses any other (averaging it would need pairs of its own).
    """

    def __init__(self, model: torch.nn.Module, decay: float, tau: float, updates: int = 0):
        self.ema = copy.deepcopy(model).eval()
        for p in self.ema.parameters():
            p.requires_grad_(False)
        self.decay, self.tau, self.updates = decay, tau, updates
        self.source = model  # the model whose tensors are paired below
        mine, theirs = dict(_tensors(self.ema)), dict(_tensors(model))
        if mine.keys() != theirs.keys():
            raise ValueError("ModelEMA: the EMA copy and the model hold different tensors")
        floating = [k for k, v in mine.items() if v.dtype.is_floating_point]
        other = [k for k, v in mine.items() if not v.dtype.is_floating_point]
        self._ema_float = [mine[k] for k in floating]
        self._model_float = [theirs[k] for k in floating]
        self._ema_other = [mine[k] for k in other]
        self._model_other = [theirs[k] for k in other]

    def decay_now(self) -> float:
        """The decay of the next update: decay * (1 - exp(-updates / tau)) lets early weights move."""
        return self.decay * (1 - math.exp(-(self.updates + 1) / self.tau))

    @torch.no_grad()
    def update(self, model: torch.nn.Module | None = None) -> None:
        """One EMA step towards `source`, the model the EMA was built from. `model` may be given
        (the usual EMA interface) but must be that very model: the step reads the tensors paired at
        construction, so another model, even an equal copy, would silently not be averaged."""
        if model is not None and model is not self.source:
            raise ValueError(f"ModelEMA.update: model is a {type(model).__name__} other than the one this EMA "
                             "was built from (its tensors are paired at construction); build a ModelEMA for it")
        d = self.decay_now()
        self.updates += 1
        torch._foreach_mul_(self._ema_float, d)
        torch._foreach_add_(self._ema_float, self._model_float, alpha=1 - d)
        if self._ema_other:
            torch._foreach_copy_(self._ema_other, self._model_other)
