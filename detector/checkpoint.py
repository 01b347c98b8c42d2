"""Checkpoints as plain data: tensors, numbers, strings, lists and dicts only.

Everything a run needs to resume or to predict is stored in forms `torch.load(weights_only=True)`
accepts, so loading a checkpoint never executes pickled code: the model configuration as a dict,
the class names, the state dicts of the model, its EMA, the optimiser, and the run's history.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import torch

from omnigen.detector.model import DetectorConfig, KeypointDetector
from omnigen.files import atomic_write_bytes
from omnigen.taxonomy import Taxonomy, load_taxonomy


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Serialise to memory, then write atomically: a kill mid-save leaves the old file intact."""
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write_bytes(path, buf.getvalue())


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such checkpoint")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for corrupt or foreign files
        raise ValueError(f"{path}: not an omnigen checkpoint ({exc.__class__.__name__}: {exc})") from None
    for key in ("config", "model", "classes"):
        if key not in state:
            raise ValueError(f"{path}: checkpoint lacks field {key!r}")
    return state


def load_model(path: str | Path) -> tuple[KeypointDetector, dict[str, Any]]:
    """The model of a checkpoint (EMA weights when present), in eval mode, and the checkpoint."""
    state = load_checkpoint(path)
    model = KeypointDetector(DetectorConfig.from_dict(state["config"]))
    model.load_state_dict(state["model"])
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
    theirs, mine = DetectorConfig.from_dict(state["config"]).to_dict(), model.cfg.to_dict()
    for key in mine:
        # the crop stage is a network of its own beside the detector: it may be added, dropped,
        # resized or told where its crops were cut without changing any detector tensor (then the
        # whole stage starts fresh: a hidden layer of new inputs under a trained one is neither)
        if key not in ("num_classes", "heading_crop", "crop_classes", "crop_split", "crop_position") and theirs.get(key) != mine[key]:
            raise ValueError(f"{path}: config field {key!r} is {theirs.get(key)!r}, this run builds {mine[key]!r}: "
                             "--weights needs the same architecture (only the classes may differ)")
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
