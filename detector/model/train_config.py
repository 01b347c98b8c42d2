"""The run's settings, TrainConfig: what `omnigen train` resolved (the recipe's fields, the run
settings, the data), stored in every checkpoint (`train_config`) and in the run's args.json.

Why it lives with the model, below training: every checkpoint records one, and prediction and
evaluation read it (the input size a model was trained at, how its run predicts) through
checkpoint.check_state, which checks its fields' types for every reader. Training builds and
resumes runs from it (training/train.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omnigen.detector.model.network import DetectorConfig
from omnigen.detector.recipe import RECIPE, RUN, train_fields

_TRAIN = train_fields(RECIPE)
"""The TrainConfig fields of the validated recipe (detector/recipe.py): the defaults below."""


@dataclass
class TrainConfig:
    """Everything a run depends on; stored in the checkpoint and in args.json.

    The fields a recipe key fills (detector/recipe.py: recipe.field_key names it) take their
    defaults from the recipe, the run's settings theirs from recipe.RunSettings: nothing here
    declares a value of its own but what only tests reach (marked below), the command's options
    that are no recipe key (the splits, --weights) and save_interval."""

    dataset: str
    out: str
    model: str = _TRAIN["model"]
    backbone: str = _TRAIN["backbone"]
    p2: bool = _TRAIN["p2"]
    p6: bool = _TRAIN["p6"]
    width: float | None = None  # tests: overrides of the scale's width and depth (tiny models)
    depth: float | None = None
    imgsz: int = _TRAIN["imgsz"]
    # train on random crop x crop windows of the imgsz input (data.random_crop); None, or a window
    # as large as the input, trains on whole images (window())
    crop: int | None = _TRAIN["crop"]
    crop_focus: float = _TRAIN["crop_focus"]  # share of the windows centred on an object drawn class-balanced
    repeat_thresh: float = _TRAIN["repeat_thresh"]  # LVIS repeat-factor sampling threshold; 0: off
    cache: bool = RUN.cache  # decode and letterbox every image once, into memory (KeypointDataset.cache_images)
    epochs: int = RUN.epochs
    batch: int = _TRAIN["batch"]
    optimizer: str = _TRAIN["optimizer"]  # adamw (decoupled weight decay) or adam (L2 decay in the gradient)
    lr0: float = _TRAIN["lr0"]
    lrf: float = _TRAIN["lrf"]  # final learning rate = lr0 * lrf (cosine)
    weight_decay: float = _TRAIN["weight_decay"]
    warmup_iters: int = _TRAIN["warmup_iters"]
    ema_decay: float = _TRAIN["ema_decay"]
    ema_tau: float = _TRAIN["ema_tau"]  # EMA ramp: decay * (1 - exp(-updates / tau)) lets early weights move
    kpt_sigma_start: float = _TRAIN["kpt_sigma_start"]  # keypoint-loss sigma annealed to kpt_sigma_end (see kpt_sigma)
    kpt_sigma_anneal: float = _TRAIN["kpt_sigma_anneal"]  # fraction of the iterations over which it is annealed
    kpt_sigma_end: float = _TRAIN["kpt_sigma_end"]  # 0.25: the OKS metric's kernel; the design's 0.125 (loss.OKS_SIGMA)
    kpt_mode: str = _TRAIN["kpt_mode"]  # corners as offsets from the anchor, or in units of the anchor's box (outputs.py)
    kpt_l1: float = _TRAIN["kpt_l1"]  # gain of the scale-free L1 corner term beside the OKS loss (loss.keypoint_l1_loss)
    kpt_labelled: float = _TRAIN["kpt_labelled"]  # gain of the OKS term in the labelled order beside the turned
    kpt_turn_start: float = _TRAIN["kpt_turn_start"]  # fraction of the run before the loss may turn corners
    kpt_heading: bool = _TRAIN["kpt_heading"]  # corners up to the turn, the front from a regressed image heading
    heading_gain: float = _TRAIN["heading_gain"]  # gain of a heading-aware head's heading term (LossGains.heading)
    heading_crop: int = _TRAIN["heading_crop"]  # crop side of the second stage (DetectorConfig.heading_crop); 0: none
    crop_classes: bool = _TRAIN["crop_classes"]  # that stage names each crop's class too (DetectorConfig.crop_classes)
    # the crop stage trained again apart as the run's second phase (recipe.CropStage, crop_train.crop_phase);
    # steps 0: the stage trained with the detector is kept
    crop_phase: dict[str, Any] = field(default_factory=lambda: dict(_TRAIN["crop_phase"]))
    taxonomy: str = _TRAIN["taxonomy"]
    train_split: str = "train"
    val_split: str | None = None  # None: 'val' if the dataset has it, else 'test', else all frames
    out_of_image: str = _TRAIN["out_of_image"]
    augment: dict[str, Any] = field(default_factory=lambda: dict(_TRAIN["augment"]))
    # how the run's model predicts (recipe.Predict): not read by training, recorded so that `omnigen
    # predict` and `eval` of its checkpoints take the run's recipe (predict.vertical=off) as theirs
    predict: dict[str, Any] = field(default_factory=lambda: dict(_TRAIN["predict"]))
    workers: int | None = RUN.workers  # None: loader.loader_workers decides by the device and its cores
    seed: int = RUN.seed
    val_every: int = RUN.val_every  # validate every N epochs and after the last; 0: never
    save_interval: float = 60.0  # seconds between last.pt writes (also written after validation and at the end)
    device: str | None = RUN.device
    amp: str = RUN.amp  # mixed precision: auto (fp16 on CUDA, off on the CPU), bf16, fp16 or off
    channels_last: bool | None = RUN.channels_last  # NHWC activations; None: on for CUDA, off on the CPU
    time_minutes: float | None = RUN.time_minutes  # wall-clock budget of the whole run; epochs is then an upper bound
    weights: str | None = None  # start from this checkpoint's (EMA) weights: a new run, not a resume

    def __post_init__(self) -> None:
        if isinstance(self.augment, dict) and isinstance(self.augment.get("hsv"), list):
            self.augment = {**self.augment, "hsv": tuple(self.augment["hsv"])}  # as JSON (args.json) spells it

    def window(self) -> int | None:
        """The side of the training windows, None for whole images (no window, or one as large as
        the input: the recipe's 320 is whole images for an input of 320 or less)."""
        return self.crop if self.crop and self.crop < self.imgsz else None

    def focus(self) -> float:
        """The share of windows centred on an object: the recipe's where there are windows, else none."""
        return self.crop_focus if self.window() else 0.0

    def model_config(self, num_classes: int) -> DetectorConfig:
        # never crop_position nor crop_split: joint training crops its augmented windows (--crop), where
        # a crop's place in the window is not its place in the image, with one CropNet; the crop
        # phase gives the position and the classes' net of their own (crop_train.attach_stage)
        return DetectorConfig(scale=self.model, backbone=self.backbone, p2=self.p2, p6=self.p6, kpt_mode=self.kpt_mode,
                              kpt_heading=self.kpt_heading, heading_crop=self.heading_crop,
                              crop_classes=self.crop_classes and self.heading_crop > 0, num_classes=num_classes,
                              width=self.width, depth=self.depth)
