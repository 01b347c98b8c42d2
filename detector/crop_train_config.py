"""How `omnigen train-crop` trains the crop stage (detector/crop_train.py): plain data, no torch,
so that the command's arguments take their defaults from it without importing torch."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class CropTrainConfig:
    """How the stage is trained. `balance` 0 draws crops uniformly, 1 gives every class an equal
    share of the draws."""

    steps: int = 4000
    batch: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4
    copies: int = 4  # crops per training object, each about its own moved box
    # uniform draws and a tenth of the joint training's heading gain (loss.LossGains.heading_crop): at
    # 2000 steps both placed the corners better than the joint training's balance and gains
    # (benchmarks/crop_apart.py, docs/detector-training.md)
    balance: float = 0.0
    heading_gain: float = 0.1
    class_gain: float = 0.5  # the joint training's (loss.LossGains.crop_cls)
    # an L1 term on the bottom face's offset from the top face (crop_train.stage_loss), what tilts a
    # lifted box most: make validate's adherence 5.07 -> 4.9 with 0.3 (docs/detector-training.md)
    offset_gain: float = 0.3
    seed: int = 0
    amp: str = "off"  # "bf16": the forward pass under CPU bfloat16 autocast (benchmarks/crop_apart.py measures it)

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
