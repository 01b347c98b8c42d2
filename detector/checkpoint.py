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

from detector.model import DetectorConfig, KeypointDetector
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
