"""How `omnigen train-crop` trains the crop stage (detector/training/crop_train.py): plain data, no torch,
so that the command's arguments take their defaults from it without importing torch."""

from __future__ import annotations

from dataclasses import dataclass

from omnigen.detector.recipe import RECIPE, RUN

_STAGE = RECIPE.crop_stage


@dataclass(frozen=True)
class CropTrainConfig:
    """How the stage is trained: the recipe's crop stage (detector/recipe.py, whose defaults are
    what make validate measured: uniform draws, a tenth of the joint
    training's heading gain, the offset term at 0.3, docs/detector-training.md). `balance` 0 draws
    crops uniformly, 1 gives every class an equal share of the draws."""

    steps: int = _STAGE.steps
    batch: int = _STAGE.batch
    lr: float = _STAGE.lr
    weight_decay: float = _STAGE.weight_decay
    copies: int = _STAGE.copies  # crops per training object, each about its own moved box
    balance: float = _STAGE.balance
    heading_gain: float = _STAGE.heading_gain
    class_gain: float = _STAGE.class_gain
    # an L1 term on the bottom face's offset from the top face (crop_train.stage_loss), what tilts a
    # lifted box most
    offset_gain: float = _STAGE.offset_gain
    seed: int = RUN.seed
    amp: str = "off"  # "bf16": the forward pass under CPU bfloat16 autocast (a machine setting, not the recipe's)

    def __post_init__(self) -> None:
        for name in ("steps", "batch", "copies"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise ValueError(f"CropTrainConfig.{name}: must be a positive integer, got {getattr(self, name)!r}")
        if not 0.0 <= self.balance <= 1.0:
            raise ValueError(f"CropTrainConfig.balance: must be between 0 and 1, got {self.balance!r}")
        for name in ("heading_gain", "class_gain", "offset_gain"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"CropTrainConfig.{name}: must be >= 0, got {getattr(self, name)!r}")
        if self.amp not in ("off", "bf16"):
            raise ValueError(f"CropTrainConfig.amp: must be 'off' or 'bf16', got {self.amp!r}")
        if not self.lr > 0:
            raise ValueError(f"CropTrainConfig.lr: must be positive, got {self.lr!r}")
