"""Checkpoints as plain data: tensors, numbers, strings, lists and dicts only.

Everything a run needs to resume or to predict is stored in forms `torch.load(weights_only=True)`
accepts, so loading a checkpoint never executes pickled code: the model configuration as a dict,
the class names, the state dicts of the model, its EMA, the optimiser, and the run's history.

A checkpoint is also an input someone may hand us: a file of another tool, a damaged copy, one
edited by hand or one of another model. Every way it can be wrong is one line naming the file and
what is wrong (not a dict, a missing field, a config field of the wrong type, tensors of another
model counted rather than listed), and never the advice to load it with weights_only=False: a
file that is not plain data is refused, not run.
"""

from __future__ import annotations

import io
import re
import types
import typing
import warnings
from dataclasses import fields
from pathlib import Path
from typing import Any, Callable, TypeVar

import torch

from omnigen.detector.model.network import DetectorConfig, KeypointDetector
from omnigen.detector.model.train_config import TrainConfig
from omnigen.detector.recipe import field_key, from_dict
from omnigen.files import atomic_write_bytes
from omnigen.taxonomy import Taxonomy, load_taxonomy
from omnigen.untrusted import open_regular

CHECKPOINT_MAX_BYTES = 16 * 2**30
"""Largest checkpoint read: the x model with its EMA and optimiser state is a few hundred MiB;
the cap keeps a path to a device or a FIFO from being read for ever."""

T = TypeVar("T")


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Serialise to memory, then write atomically: a kill mid-save leaves the old file intact, and
    a failed write removes its temporary file (omnigen.files.atomic_write_bytes)."""
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write_bytes(path, buf.getvalue())


def _first_sentence(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else exc.__class__.__name__
    return text.split(". ")[0].rstrip(".")


def load_plain(path: str | Path) -> Any:
    """What a torch file holds, loaded as plain data only (`weights_only=True`); one line naming
    the file for anything else. Torch's own refusal of a pickled object advises loading with
    weights_only=False, which would run the file's code: that advice is left out."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such checkpoint")
    with open_regular(path, CHECKPOINT_MAX_BYTES) as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch warns about the pickle protocol of foreign files
        try:
            return torch.load(fh, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises several types for damaged or foreign files
            raise ValueError(f"{path}: {_load_error(exc)}") from None


def _load_error(exc: Exception) -> str:
    """Why torch.load refused a file, in a clause of our own words (torch's are several lines)."""
    text = str(exc)
    found = re.search(r"GLOBAL ([\w.]+)", text)
    if found:
        return (f"holds a Python object ({found.group(1)}), not only tensors, numbers, strings, lists and dicts; "
                "omnigen loads only such plain-data checkpoints")
    if "weights_only" in text or "Weights only" in text:
        return "not an omnigen checkpoint (a pickle of something other than plain data)"
    return f"not an omnigen checkpoint ({exc.__class__.__name__}: {_first_sentence(exc)})"


def _shown(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def a_kind(value: Any) -> str:
    """"an int", "a Tensor": what a file holds where a dict was expected."""
    name = type(value).__name__
    return f"{'an' if name[0].lower() in 'aeiou' else 'a'} {name}"


def _type_name(hint: Any) -> str:
    return hint.__name__ if isinstance(hint, type) else str(hint).replace("typing.", "")


def _fits(value: Any, hint: Any) -> bool:
    """Whether a stored value has a dataclass field's annotated type (bool is no int here, an int
    is a float: JSON and older writers store 1 for 1.0)."""
    if hint is Any:
        return True
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return any(_fits(value, arg) for arg in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, typing.get_origin(hint) or hint)


def check_types(path: str | Path, field: str, data: Any, cls: type, unknown_ok: bool = False) -> dict[str, Any]:
    """`data`, a dict of the dataclass `cls`'s fields, each of its annotated type; else one line
    naming the file and the field. `unknown_ok` passes fields `cls` does not have (a newer or
    older writer's) untouched."""
    if not isinstance(data, dict):
        raise ValueError(f"{path}: {field} is {a_kind(data)}, expected a dict of {cls.__name__} fields")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in fields(cls)}
    unknown = sorted(map(str, (k for k in data if k not in known)))
    if unknown and not unknown_ok:
        raise ValueError(f"{path}: {field} has fields {cls.__name__} does not know: {', '.join(unknown)}")
    for key, value in data.items():
        if key in known and not _fits(value, hints[key]):
            raise ValueError(f"{path}: {field}.{key} is {_shown(value)}, not of type {_type_name(hints[key])}")
    return data


def checked_fields(path: str | Path, field: str, data: Any, cls: Callable[..., T]) -> T:
    """The dataclass `cls` built from `data` (check_types first, then its own validation), or one
    line naming the file and the field."""
    check_types(path, field, data, cls)
    try:
        return cls(**data)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {field}: {exc}") from None


def check_tensors(path: str | Path, field: str, tensors: Any) -> dict[str, torch.Tensor]:
    """A state dict: names to tensors."""
    if not isinstance(tensors, dict):
        raise ValueError(f"{path}: {field} is {a_kind(tensors)}, expected a dict of tensors")
    for key, value in tensors.items():
        if not isinstance(key, str) or not isinstance(value, torch.Tensor):
            raise ValueError(f"{path}: {field}[{_shown(key)}] is {a_kind(value)}, not a tensor")
    return tensors


def detector_config(path: str | Path, state: dict[str, Any]) -> DetectorConfig:
    """The checkpoint's model configuration, checked field by field."""
    return checked_fields(path, "config", state["config"], DetectorConfig)


def check_state(path: str | Path, state: Any) -> dict[str, Any]:
    """A loaded checkpoint as prediction, evaluation and training read it: a dict with a valid
    config, class names as many as the config's classes, a state dict of tensors, and where present
    a valid taxonomy of those classes and a dict of training settings."""
    if not isinstance(state, dict):
        raise ValueError(f"{path}: holds {a_kind(state)}, not an omnigen checkpoint "
                         "(a dict of config, model and classes)")
    for key in ("config", "model", "classes"):
        if key not in state:
            raise ValueError(f"{path}: checkpoint lacks field {key!r}")
    cfg = detector_config(path, state)
    classes = state["classes"]
    if not isinstance(classes, list) or not all(isinstance(c, str) for c in classes):
        raise ValueError(f"{path}: classes is {_shown(classes)}, expected a list of class names")
    if len(classes) != cfg.num_classes:
        raise ValueError(f"{path}: classes names {len(classes)} classes, config.num_classes is {cfg.num_classes}")
    check_tensors(path, "model", state["model"])
    if "taxonomy" in state:
        taxonomy = Taxonomy.from_dict(state["taxonomy"], path, "taxonomy")
        if taxonomy.classes != classes:
            raise ValueError(f"{path}: taxonomy's classes {taxonomy.classes} are not the checkpoint's {classes}")
    if "train_config" in state:
        check_types(path, "train_config", state["train_config"], TrainConfig, unknown_ok=True)
        if "predict" in state["train_config"]:  # what prediction takes as its defaults (trained_vertical)
            from_dict({"predict": state["train_config"]["predict"]}, f"{path}: train_config.predict")
    return state


SCHEMA = 2
"""The version of what a checkpoint records (state["schema"]). 1, unmarked: written before the
recipe (detector/recipe.py) gave `omnigen train` its defaults; its records may lack fields that
were added later, and a field it lacks is read as what the code did then (V1_DEFAULTS). 2: every
record complete."""

V1_DEFAULTS: dict[str, dict[str, Any]] = {
    # TrainConfig as it stood before schema 2: the design's plain branch, Adam before the optimizer
    # was a choice, no crop phase (omnigen train-crop was a command of its own)
    "train_config": {
        "model": "n", "backbone": "c3k2", "p2": True, "p6": False, "width": None, "depth": None, "imgsz": 640,
        "crop": None, "crop_focus": 0.0, "repeat_thresh": 0.0, "cache": False, "epochs": 100, "batch": 16,
        "optimizer": "adam", "lr0": 2e-3, "lrf": 0.01, "weight_decay": 5e-4, "warmup_iters": 100,
        "ema_decay": 0.9999, "ema_tau": 2000.0, "kpt_sigma_start": 0.5, "kpt_sigma_anneal": 0.3,
        "kpt_sigma_end": 0.125, "kpt_mode": "anchor", "kpt_l1": 0.0,
        "kpt_labelled": 0.0, "kpt_turn_start": 0.0, "kpt_heading": False, "heading_gain": 1.0, "heading_crop": 0,
        "crop_classes": False, "crop_phase": {"steps": 0}, "taxonomy": "fine",
        "train_split": "train", "val_split": None, "out_of_image": "learn",
        "augment": {"flip": 0.5, "scale": 0.5, "translate": 0.1, "hsv": [0.015, 0.7, 0.4]}, "workers": 2,
        "seed": 0, "val_every": 1, "save_interval": 60.0, "device": None, "amp": "auto", "channels_last": None,
        "time_minutes": None, "weights": None},
    # omnigen train-crop's record of the stage it trained: no position before --position, no
    # offset term before --offset-gain
    "crop_stage": {"position": False},
    "crop_stage.config": {"offset_gain": 0.0},
}


REMOVED: dict[str, dict[str, Any]] = {
    # a turn logit beside the corners (kpt_turn), a wider keypoint branch (kpt_hidden), the crop
    # stage's classes from a net of their own while training with the detector (crop_split):
    # measured and not kept (docs/detector-training.md, "What justified it")
    "config": {"kpt_turn": False, "kpt_hidden": None},
    "train_config": {"kpt_turn": False, "kpt_hidden": None, "crop_split": False},
}
"""Fields of branches this version no longer has, with the value each recorded while its branch was
off (False, None). Checkpoints of either schema that record them so, as every run of the recipe
did, are read without them; one trained with a branch is refused by name (`upgraded`): its
tensors, or the run it would resume, need code that is gone."""


def plain_branch() -> dict[str, Any]:
    """TrainConfig's recipe fields as the design's plain branch (V1_DEFAULTS, AdamW): what the
    trainer's mechanics are measured and tested with, apart from the validated recipe (no heading,
    no crop stage, no crop phase)."""
    return {**{k: v for k, v in V1_DEFAULTS["train_config"].items() if field_key(k) or k == "crop_phase"},
            "optimizer": "adamw"}


def upgraded(path: str | Path, state: Any) -> Any:
    """A checkpoint's records as this version reads them, one table for each way an older writer
    differs: the fields of removed branches left out (REMOVED; one recorded on is one line naming
    the file and the field), and a schema-1 one's records completed with what it was trained with
    (V1_DEFAULTS), marked schema 2. Anything else, and what is not a dict, as it is: check_state
    and load_checkpoint say what is wrong with it."""
    if not isinstance(state, dict):
        return state
    out = dict(state)
    for part, removed in REMOVED.items():
        record = state.get(part)
        if not isinstance(record, dict):
            continue
        for key, off in removed.items():
            if key in record and record[key] is not off:  # False and None: one object each
                raise ValueError(f"{path}: trained with {key}, a branch this version does not have "
                                 f"({part}.{key} is {_shown(record[key])})")
        out[part] = {k: v for k, v in record.items() if k not in removed}
    schema = state.get("schema", 1)
    if type(schema) is not int or schema != 1:  # a newer one, or one load_checkpoint refuses
        return out
    if isinstance(out.get("train_config"), dict):
        out["train_config"] = {**V1_DEFAULTS["train_config"], **out["train_config"]}
    if isinstance(out.get("crop_stage"), dict):
        stage = {**V1_DEFAULTS["crop_stage"], **out["crop_stage"]}
        if isinstance(stage.get("config"), dict):
            stage["config"] = {**V1_DEFAULTS["crop_stage.config"], **stage["config"]}
        out["crop_stage"] = stage
    out["schema"] = SCHEMA
    return out


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """A checkpoint file read as this version's (upgraded), checked (check_state): every error one
    line naming the file."""
    state = check_state(path, upgraded(path, load_plain(path)))
    schema = state.get("schema", 1)
    if not isinstance(schema, int) or isinstance(schema, bool) or not 1 <= schema <= SCHEMA:
        raise ValueError(f"{path}: schema is {_shown(state.get('schema'))}, not one this omnigen reads "
                         f"(1 to {SCHEMA}; a newer omnigen wrote it?)")
    return state


def load_weights(module: torch.nn.Module, tensors: dict[str, torch.Tensor], path: str | Path,
                 field: str = "model") -> None:
    """Load a state dict into `module`, or one line naming the file that counts the tensors that do
    not fit (load_state_dict lists every one of them: tens of kilobytes for another model size)."""
    mine = module.state_dict()
    missing = [k for k in mine if k not in tensors]
    unexpected = [k for k in tensors if k not in mine]
    shaped = [k for k in mine if k in tensors and tuple(tensors[k].shape) != tuple(mine[k].shape)]
    parts = []
    if shaped:
        k = shaped[0]
        parts.append(f"{len(shaped)} of {len(mine)} have other shapes (first {k}: {tuple(tensors[k].shape)} "
                     f"there, {tuple(mine[k].shape)} here)")
    if missing:
        parts.append(f"{len(missing)} missing (first {missing[0]})")
    if unexpected:
        parts.append(f"{len(unexpected)} unexpected (first {unexpected[0]})")
    if parts:
        raise ValueError(f"{path}: its {field} tensors do not fit the model: {'; '.join(parts)}")
    module.load_state_dict(tensors)


def load_part(path: str | Path, field: str, load: Callable[[], Any]) -> Any:
    """Run `load` (an optimiser's, scheduler's or generator's load_state_dict on a field of the
    checkpoint), its refusal one line naming the file and the field."""
    try:
        return load()
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{path}: {field} does not fit this run ({exc.__class__.__name__}: "
                         f"{_first_sentence(exc)})") from None


def config_difference(path: str | Path, theirs: DetectorConfig, mine: DetectorConfig, skip: tuple[str, ...] = (),
                      why: str = "") -> None:
    """Refuse the first field (but `skip`) in which a checkpoint's model config differs from the
    model built here, naming the file and the field (then `why`): its tensors mean other things."""
    theirs_d, mine_d = theirs.to_dict(), mine.to_dict()
    for key in mine_d:
        if key not in skip and theirs_d.get(key) != mine_d[key]:
            raise ValueError(f"{path}: config field {key!r} is {theirs_d.get(key)!r}, this run builds "
                             f"{mine_d[key]!r}{why}")


def load_model(path: str | Path) -> tuple[KeypointDetector, dict[str, Any]]:
    """The model of a checkpoint (EMA weights when present), in eval mode, and the checkpoint."""
    state = load_checkpoint(path)
    model = KeypointDetector(detector_config(path, state))
    load_weights(model, state["model"], path)
    return model.eval(), state


def checkpoint_taxonomy(state: dict[str, Any]) -> Taxonomy:
    """The classes a checkpoint was trained on (checkpoints without the field: the fine taxonomy)."""
    return Taxonomy.from_dict(state["taxonomy"]) if "taxonomy" in state else load_taxonomy("fine")


def load_pretrained(model: KeypointDetector, path: str | Path, taxonomy: Taxonomy) -> list[str]:
    """Load an earlier run's weights (its EMA model) into a fresh `model` for a new run; returns notes.

    Why it is not a resume: fine-tuning (e.g. a model pretrained on a large synthetic set, then
    real data: the design's Table 8 setting) wants the weights and nothing else: a fresh optimiser,
    a new schedule from epoch 0, possibly other classes.
    The architecture must be the same (every DetectorConfig field but num_classes and the crop
    stage's, heading_crop, crop_classes, crop_split and crop_position: the crop stage's tensors start fresh where
    the checkpoint has none of their shape): otherwise the
    tensors mean other things, and the refusal names the file and the field. Where the classes
    differ, the class branches' last layers get the checkpoint's rows of the classes both
    taxonomies name, and keep the fresh initialisation for the others; any class-branch tensor
    whose shape still differs stays freshly initialised. The notes say what was re-initialised.
    """
    state = load_checkpoint(path)
    # the crop stage is a network of its own beside the detector: it may be added, dropped,
    # resized or told where its crops were cut without changing any detector tensor (then the
    # whole stage starts fresh: a hidden layer of new inputs under a trained one is neither)
    theirs_cfg = detector_config(path, state)
    config_difference(path, theirs_cfg, model.cfg,
                      skip=("num_classes", "heading_crop", "crop_classes", "crop_split", "crop_position"),
                      why=": --weights needs the same architecture (only the classes may differ)")
    theirs, mine = theirs_cfg.to_dict(), model.cfg.to_dict()
    src = state["model"]
    dst = model.state_dict()
    old_classes = list(state["classes"])
    new_classes = list(taxonomy.classes)
    other_stage = (theirs.get("heading_crop") != mine["heading_crop"]
                   or bool(theirs.get("crop_position")) != bool(mine["crop_position"]))
    last_layers = {f"head.cls.{i}.{len(branch) - 1}.{name}"
                   for i, branch in enumerate(model.head.cls) for name in ("weight", "bias")}
    fresh, partial, fresh_crop = [], [], []
    loaded: dict[str, torch.Tensor] = {}
    for key, value in dst.items():
        if key in last_layers and old_classes != new_classes:
            rows = [(new_classes.index(c), old_classes.index(c)) for c in new_classes if c in old_classes]
            if rows and key in src and src[key].shape[1:] == value.shape[1:]:
                to, frm = zip(*rows)
                loaded[key] = value.clone()
                loaded[key][list(to)] = src[key][list(frm)].to(value.dtype)
                partial.append(key)
            else:
                fresh.append(key)
        elif key.startswith("crop_net.") and other_stage:
            fresh_crop.append(key)
        elif key.startswith(("crop_net.out.", "crop_net.classes.out.")) and model.cfg.crop_classes \
                and old_classes != new_classes:
            fresh_crop.append(key)  # its last rows are classes, and other ones
        elif key in src and src[key].shape == value.shape:
            loaded[key] = src[key]
        elif key.startswith("head.cls."):
            fresh.append(key)
        elif key.startswith("crop_net."):
            fresh_crop.append(key)
        else:
            raise ValueError(f"{path}: tensor {key!r} is missing or has shape "
                             f"{tuple(src[key].shape) if key in src else None}, this model's is {tuple(value.shape)}")
    model.load_state_dict({**dst, **loaded})
    notes = []
    if old_classes != new_classes:
        kept = [c for c in new_classes if c in old_classes]
        layers = (f"keep the checkpoint's rows of {kept} and start fresh for the other classes" if kept
                  else "start fresh (no class in common)")
        notes.append(f"{path}: trained on classes {old_classes}, this run has {new_classes}; "
                     f"the class branches' last layers {layers}")
    if fresh:
        notes.append(f"{path}: re-initialised {len(fresh)} class-head tensor(s): {', '.join(fresh)}")
    if fresh_crop:
        notes.append(f"{path}: has no crop stage of this shape (its crop side, whether it is told where its crops "
                     f"were cut, or the classes it names); "
                     f"the stage starts fresh where it differs ({len(fresh_crop)} tensors: {', '.join(fresh_crop)})")
    if partial:
        notes.append(f"{path}: re-initialised the rows of new classes in {', '.join(partial)}")
    return notes
