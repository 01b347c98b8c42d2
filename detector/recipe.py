"""The detector's recipe: one typed, frozen set of values, and its defaults are the validated model.

Why one place. The recipe used to be written five times (train's flags, TrainConfig, make
validate's flags, two benchmarks' copies) and the plain `omnigen train DATA --out RUN` trained
none of them. Here, as in Ultralytics' single defaults file, every value that decides what is
learned has one default: exactly what `make validate` trained for docs/RESULTS.md (nano with P2 at
640, 320-pixel windows half centred class-balanced, repeat-factor sampling at 0.3, AdamW at 2e-3,
the keypoints in box units annealed to sigma 0.25 with an L1 term, the image heading, a 64-pixel
crop stage that names classes, then that stage trained again for 7000 steps on clean crops).
TrainConfig, CropTrainConfig and the options of `omnigen train` and `omnigen train-crop` take their
defaults from here (tests/detector/test_recipe.py fails where one of them re-declares one).

What is not in it. How fast and where a run goes (device, loader workers, precision, the time
budget, epochs, the validation cadence, the image cache, the seed) are `RunSettings`: they are the
machine's and the budget's, not the model's.

How a user reaches it. `omnigen train DATASET --out RUN [KEY=VALUE ...]` overrides keys
(`loss.kpt_l1=1.5`, `data.window=0`); `--recipe FILE` starts from a recipe file such as the
RUN/recipe.json every run writes (its resolved recipe, first key "omnigen": "train"), the keys
given on the command line applied over it. A key that does not exist, or a value of the wrong type
or outside its range, is one line naming the key (and the file). This module is plain data: no
torch, so `omnigen train --help` lists the keys without importing it.
"""

from __future__ import annotations

import argparse
import json
import math
import typing
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable

from omnigen.options import fraction, integer, number

GAIN_MAX = 1000.0
"""Largest loss gain accepted: a term weighed more than that drowns every other one."""
RECIPE_FILE = "recipe.json"
"""The resolved recipe a run writes into its folder."""
JOB = "train"
"""The mark of a recipe file omnigen wrote (omnigen.outputs: its first key, "omnigen": "train")."""


def choice(*options: str) -> Callable[[str], str]:
    """A string that is one of `options`, as argparse's choices say it."""
    def parse(text: str) -> str:
        if text not in options:
            raise argparse.ArgumentTypeError(f"{text!r} is not one of {', '.join(options)}")
        return text

    parse.__name__ = "choice"
    return parse


def switch(text: str) -> bool:
    """true/false (also 1/0, yes/no, on/off)."""
    words = {"true": True, "1": True, "yes": True, "on": True, "false": False, "0": False, "no": False, "off": False}
    if text.lower() not in words:
        raise argparse.ArgumentTypeError(f"{text!r} is not true or false")
    return words[text.lower()]


def text(value: str) -> str:
    """Any non-empty string (a taxonomy preset or a TOML file)."""
    if not value:
        raise argparse.ArgumentTypeError("is empty")
    return value


def triple(part: Callable[[str], float]) -> Callable[[str], tuple[float, float, float]]:
    """Three comma-separated numbers, each checked by `part`."""
    def parse(value: str) -> tuple[float, float, float]:
        items = [s.strip() for s in value.split(",")]
        if len(items) != 3:
            raise argparse.ArgumentTypeError(f"{value!r} is not three comma-separated numbers")
        a, b, c = (part(s) for s in items)
        return (a, b, c)

    return parse


def knob(default: Any, check: Callable[[str], Any], help: str, to: str | None = None) -> Any:
    """A recipe field: its default, the parser of a command-line value (omnigen.options' types,
    which name the range), a line of help, and the TrainConfig field it fills (`to`; none for a key
    that a TrainConfig dict keeps by its name: augment's, the crop stage's training, predict's, NESTED)."""
    return field(default=default, metadata={"check": check, "help": help, "to": to})


GAIN = number(0.0, GAIN_MAX)
SIGMA = number(0.0, 10.0, lo_open=True)


@dataclass(frozen=True)
class Model:
    """The network."""

    scale: str = knob("n", choice("n", "s", "m", "l", "x"), "width and depth scale", "model")
    backbone: str = knob("c3k2", choice("c3k2", "c2f"), "backbone family: c3k2 (YOLO11-style) or c2f (YOLOv8-style)",
                         "backbone")
    p2: bool = knob(True, switch, "a stride-4 level for small objects", "p2")
    p6: bool = knob(False, switch, "a stride-64 level", "p6")
    imgsz: int = knob(640, integer(32, 8192), "input size: images are letterboxed to it (validation and prediction too)",
                      "imgsz")
    kpt_mode: str = knob("box", choice("anchor", "box"),
                         "corners as offsets from the anchor, or in units of the anchor's predicted box", "kpt_mode")
    heading: bool = knob(True, switch, "learn corners up to the 180-degree turn and the front from a regressed "
                         "image heading (detector/model/heading.py)", "kpt_heading")


@dataclass(frozen=True)
class Data:
    """What a training step sees."""

    window: int = knob(320, integer(0, 8192), "train on random WINDOW x WINDOW windows of the input: objects keep the "
                       "scale they are predicted at; 0, or one as large as the input: whole images", "crop")
    focus: float = knob(0.5, fraction(), "with windows: centre this share of them on an object drawn class-balanced "
                        "(detector/data/balance.py)", "crop_focus")
    repeat_thresh: float = knob(0.3, fraction(), "repeat-factor sampling (LVIS): a frame whose rarest class is in a "
                                "fraction f < T of the training frames is drawn sqrt(T / f) times an epoch; 0: off",
                                "repeat_thresh")
    taxonomy: str = knob("fine", text, "class taxonomy preset or TOML file", "taxonomy")
    out_of_image: str = knob("learn", choice("learn", "drop"), "corners outside the image but in front of the "
                             "camera: learn them or mask them", "out_of_image")


@dataclass(frozen=True)
class Augment:
    """Training augmentation (0 everywhere: letterbox only)."""

    flip: float = knob(0.5, fraction(), "probability of a horizontal flip")
    scale: float = knob(0.5, fraction(), "random zoom in [1 - scale, 1 + scale]")
    translate: float = knob(0.1, fraction(), "random shift, a fraction of the input size")
    hsv: tuple[float, float, float] = knob((0.015, 0.7, 0.4), triple(fraction()),
                                           "hue, saturation and value jitter gains (H,S,V)")


@dataclass(frozen=True)
class Optim:
    """The optimiser."""

    optimizer: str = knob("adamw", choice("adamw", "adam"),
                          "adamw (decoupled weight decay) or adam (weight decay in the gradient)", "optimizer")
    batch: int = knob(16, integer(1, 4096), "images a step, over all processes", "batch")
    lr0: float = knob(2e-3, number(0.0, 1.0, lo_open=True), "peak learning rate (cosine decay to lr0 * lrf)", "lr0")
    lrf: float = knob(0.01, fraction(), "final learning rate, a fraction of lr0", "lrf")
    weight_decay: float = knob(5e-4, number(0.0, 1.0), "weight decay of conv and linear weights", "weight_decay")
    warmup_iters: int = knob(100, integer(0, 10_000_000), "steps of linear warm-up", "warmup_iters")
    ema_decay: float = knob(0.9999, fraction(), "decay of the EMA weights that are saved and validated", "ema_decay")
    ema_tau: float = knob(2000.0, number(0.0, 1e9, lo_open=True), "EMA ramp: decay * (1 - exp(-updates / tau))",
                          "ema_tau")


@dataclass(frozen=True)
class Schedule:
    """What changes along the run (fractions of its steps)."""

    kpt_sigma_start: float = knob(0.5, SIGMA, "keypoint-loss sigma at the start", "kpt_sigma_start")
    kpt_sigma_end: float = knob(0.25, SIGMA, "keypoint-loss sigma after the anneal: 0.25 is the OKS metric's kernel, "
                                "0.125 the design's formula read literally", "kpt_sigma_end")
    kpt_sigma_anneal: float = knob(0.3, fraction(), "fraction of the run the sigma anneal takes", "kpt_sigma_anneal")
    kpt_turn_start: float = knob(0.3, fraction(), "fraction of the run in which corners are compared as labelled "
                                 "only, before a heading-aware loss may turn them", "kpt_turn_start")


@dataclass(frozen=True)
class Loss:
    """Gains of the loss terms beside the design's (box 7.5, dfl 1.5, cls 0.5, kpt 6, kvis 1)."""

    kpt_l1: float = knob(2.0, GAIN, "a scale-free L1 corner term beside the OKS keypoint loss", "kpt_l1")
    kpt_labelled: float = knob(1.0, GAIN, "the OKS loss in the labelled order beside the one up to the turn: a pull "
                               "towards the true heading", "kpt_labelled")
    heading: float = knob(1.0, GAIN, "the image heading's term", "heading_gain")


@dataclass(frozen=True)
class CropStage:
    """The second stage that places each object's corners, front and class from a crop of it
    (detector/model/crop_stage.py): trained with the detector, then again apart on clean crops for
    `steps` (detector/training/crop_train.py), the run's second phase."""

    side: int = knob(64, integer(0, 1024), "crop side in pixels, a multiple of 16; 0: no crop stage", "heading_crop")
    classes: bool = knob(True, switch, "the stage names each crop's class and prediction rescores by it",
                         "crop_classes")
    steps: int = knob(7000, integer(0, 10_000_000), "steps of the second phase, the stage trained again apart on "
                      "clean crops; 0: keep the stage trained with the detector")
    batch: int = knob(64, integer(1, 65536), "crops a step of the second phase")
    lr: float = knob(2e-3, number(0.0, 1.0, lo_open=True), "peak learning rate of its one-cycle schedule")
    weight_decay: float = knob(1e-4, number(0.0, 1.0), "its AdamW weight decay")
    copies: int = knob(4, integer(1, 1000), "crops per training object, each about its own moved box")
    balance: float = knob(0.0, fraction(), "draw a crop with weight (crops of its class)^-balance: 0 uniform")
    heading_gain: float = knob(0.1, GAIN, "gain of its heading term beside the corners'")
    class_gain: float = knob(0.5, GAIN, "gain of its class term")
    offset_gain: float = knob(0.3, GAIN, "gain of an L1 term on the bottom face's offset from the top face")
    position: bool = knob(True, switch, "tell the stage where each crop was cut from its input")
    split: bool = knob(True, switch, "with classes: name them with a crop net of their own")


@dataclass(frozen=True)
class Predict:
    """How the published figures were predicted (omnigen predict, eval)."""

    vertical: str = knob("lines", choice("lines", "off"), "turn each image's vertical edges to its vertical "
                         "vanishing point (detector/prediction/vanishing.py); off: the network's corners")


@dataclass(frozen=True)
class Recipe:
    """Everything that decides what a run learns; its defaults are the validated model."""

    model: Model = Model()
    data: Data = Data()
    augment: Augment = Augment()
    optim: Optim = Optim()
    schedule: Schedule = Schedule()
    loss: Loss = Loss()
    crop_stage: CropStage = CropStage()
    predict: Predict = Predict()


@dataclass(frozen=True)
class RunSettings:
    """Where and how fast a run goes, and its budget: the machine's, not the model's.

    The epochs are the recipe's schedule when no --time budget cuts it: 150 took make validate's
    482 frames 95 minutes on 2 CPU cores; `omnigen train` says after the first epoch how long the
    run will take and points at --time when that is hours. Validation every 10 epochs (and after
    the last) keeps it a small share of a CPU run."""

    epochs: int = 150
    time_minutes: float | None = None
    val_every: int = 10
    workers: int | None = None  # None: none on a CPU of 2 cores or fewer, else 2 (data/loader.py loader_workers)
    device: str | None = None
    amp: str = "auto"
    cache: bool = False
    seed: int = 0
    channels_last: bool | None = None


RECIPE = Recipe()
RUN = RunSettings()


# -- keys ---------------------------------------------------------------------------------------------

def sections() -> dict[str, type]:
    """Section name -> its dataclass (the annotations are strings here: resolved)."""
    hints = typing.get_type_hints(Recipe)
    return {f.name: hints[f.name] for f in fields(Recipe)}


def knobs() -> dict[str, Any]:
    """'section.key' -> its dataclass field (metadata: check, help, to)."""
    return {f"{name}.{f.name}": f for name, cls in sections().items() for f in fields(cls)}


def flat(recipe: Recipe) -> dict[str, Any]:
    """'section.key' -> value."""
    return {f"{name}.{k}": v for name, part in asdict(recipe).items() for k, v in part.items()}


def key_error(key: str) -> str:
    """Why `key` is not a recipe key, with the keys of its section (or the sections) to choose from."""
    section = key.split(".", 1)[0]
    names = sections()
    if section in names:
        return f"{key}: no such recipe key; {section} has {', '.join(f.name for f in fields(names[section]))}"
    return f"{key}: no such recipe key (sections: {', '.join(names)})"


def with_values(recipe: Recipe, values: dict[str, Any]) -> Recipe:
    """`recipe` with the flat keys of `values` replaced (already checked)."""
    parts = {name: {} for name in sections()}
    for key, value in values.items():
        section, name = key.split(".", 1)
        parts[section][name] = value
    return replace(recipe, **{s: replace(getattr(recipe, s), **v) for s, v in parts.items() if v})


def parse_value(key: str, raw: str) -> Any:
    """A command-line value of `key`, checked by its field's parser; one line naming the key."""
    spec = knobs().get(key)
    if spec is None:
        raise ValueError(key_error(key))
    try:
        return spec.metadata["check"](raw)
    except argparse.ArgumentTypeError as exc:
        raise ValueError(f"{key}: {exc}") from None


def with_overrides(recipe: Recipe, overrides: list[str]) -> Recipe:
    """`recipe` with each KEY=VALUE of `overrides` applied, left to right."""
    values = {}
    for item in overrides:
        key, eq, raw = item.partition("=")
        if not eq or not key:
            raise ValueError(f"{item!r}: not KEY=VALUE (a recipe key such as loss.kpt_l1=1.5; the keys are in "
                             "'omnigen train --help')")
        values[key.strip()] = parse_value(key.strip(), raw.strip())
    return with_values(recipe, values)


def _as_text(value: Any) -> str | None:
    """A JSON value as the command line would spell it, for its field's parser; None for a kind no
    field takes (objects, null)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)) and not (isinstance(value, float) and not math.isfinite(value)):
        return repr(value)
    if isinstance(value, str):
        return value
    if isinstance(value, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        return ",".join(map(repr, value))
    return None


def _check_stored(key: str, value: Any, where: str) -> Any:
    """A stored value of `key`, of its field's type and in its range; one line naming the file and the key."""
    spec = knobs()[key]
    hint = typing.get_type_hints(type(getattr(RECIPE, key.split(".")[0])))[spec.name]
    kind = {bool: bool, int: int, float: (int, float), str: str}.get(hint, list)
    raw = _as_text(value)
    wrong = raw is None or not isinstance(value, kind) or (hint is not bool and isinstance(value, bool))
    if wrong:
        raise ValueError(f"{where}: {key} is {json.dumps(value)[:60]}, not {_kind_name(hint)}")
    try:
        parsed = spec.metadata["check"](raw)
    except argparse.ArgumentTypeError as exc:
        raise ValueError(f"{where}: {key}: {exc}") from None
    return float(parsed) if hint is float else parsed


def _kind_name(hint: Any) -> str:
    return {bool: "true or false", int: "a whole number", float: "a number", str: "a string"}.get(
        hint, "a list of three numbers")


def from_dict(data: Any, where: str, base: Recipe = RECIPE) -> Recipe:
    """The recipe a JSON object of sections holds (the keys it leaves out keep `base`'s), every
    key and value checked; `where` names the file in errors. An "omnigen" key (the mark) is passed."""
    if not isinstance(data, dict):
        raise ValueError(f"{where}: holds {type(data).__name__}, not a recipe (an object of sections)")
    values = {}
    for section, part in data.items():
        if section == "omnigen":
            continue
        if section not in sections():
            raise ValueError(f"{where}: {key_error(str(section))}")
        if not isinstance(part, dict):
            raise ValueError(f"{where}: {section} is {type(part).__name__}, not an object of keys")
        for name, value in part.items():
            key = f"{section}.{name}"
            if key not in knobs():
                raise ValueError(f"{where}: {key_error(key)}")
            values[key] = _check_stored(key, value, where)
    return with_values(base, values)


RECIPE_MAX_BYTES = 1 << 20
"""Largest recipe file read: a resolved recipe is about 2 KB."""


def read_recipe(path: str | Path) -> Recipe:
    """A recipe file (RUN/recipe.json of an earlier run, or one written by hand), checked."""
    from omnigen.untrusted import open_regular

    try:
        with open_regular(Path(path), RECIPE_MAX_BYTES) as fh:
            data = json.loads(fh.read())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not a JSON recipe ({exc.msg} at line {exc.lineno})") from None
    return from_dict(data, str(path))


def resolve(recipe_file: str | Path | None, overrides: list[str]) -> Recipe:
    """The recipe a command line names: `--recipe FILE`'s (else the validated one) with its KEY=VALUE
    overrides applied, as `omnigen train` and the benchmarks that drive it resolve it."""
    return with_overrides(read_recipe(recipe_file) if recipe_file else RECIPE, overrides)


def recipe_json(recipe: Recipe) -> str:
    """The recipe file's text: the mark first (omnigen.outputs.json_made_by), then each section."""
    return json.dumps({"omnigen": JOB, **asdict(recipe)}, indent=2, allow_nan=False) + "\n"


# -- TrainConfig ---------------------------------------------------------------------------------------

NESTED = {"augment": "augment", "crop_stage": "crop_phase", "predict": "predict"}
"""Recipe section -> the TrainConfig dict that keeps those of its keys no field of its own takes
(augmentation, the crop stage's second phase, how the run's model predicts): a checkpoint and
recipe.json record the whole recipe, predict's keys included, which `omnigen predict` and `eval`
then take as their defaults."""


def _slot(key: str) -> tuple[str, str | None]:
    """Where TrainConfig keeps a recipe key: its `to` field (None), or a key of a NESTED dict."""
    to = knobs()[key].metadata["to"]
    section, name = key.split(".")
    return (to, None) if to else (NESTED[section], name)


def train_fields(recipe: Recipe) -> dict[str, Any]:
    """The TrainConfig fields of a recipe (each key at its `_slot`); data.window 0 is no window (None)."""
    out: dict[str, Any] = {name: {} for name in NESTED.values()}
    for key, value in flat(recipe).items():
        field_name, name = _slot(key)
        if name is None:
            out[field_name] = value
        else:
            out[field_name][name] = value
    out["crop"] = out["crop"] or None
    return out


def recipe_of(config: dict[str, Any]) -> Recipe:
    """The recipe of TrainConfig fields (`asdict(cfg)`), train_fields' inverse: what a run records as
    RUN/recipe.json. Keys it lacks (a checkpoint written before predict's were kept) keep the
    default recipe's values."""
    values = {}
    for key in knobs():
        field_name, name = _slot(key)
        part, name = (config, field_name) if name is None else (config.get(field_name, {}), name)
        if name in part:
            values[key] = tuple(part[name]) if isinstance(part[name], list) else part[name]  # hsv as JSON spells it
    if "data.window" in values:
        values["data.window"] = values["data.window"] or 0
    return with_values(RECIPE, values)


def field_key(train_field: str) -> str | None:
    """The recipe key that fills a TrainConfig field ('lr0' -> 'optim.lr0'), None for other fields."""
    return next((k for k, spec in knobs().items() if spec.metadata["to"] == train_field), None)


def describe() -> str:
    """Every key with its default, for `omnigen train --help`."""
    lines = ["recipe keys (KEY=VALUE; defaults: the validated model, docs/RESULTS.md):"]
    values = flat(RECIPE)
    for key, spec in knobs().items():
        value = values[key]
        shown = ",".join(map(str, value)) if isinstance(value, tuple) else str(value).lower() \
            if isinstance(value, bool) else str(value)
        lines.append(f"  {key}={shown}: {spec.metadata['help']}")
    return "\n".join(lines)
