"""Checkpoints of branches this version no longer has (checkpoint.REMOVED): read where the branch
was off, refused by name where a run was trained with it."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from omnigen.detector.model.checkpoint import load_checkpoint, load_model, save_checkpoint

OFF_CONFIG = {"kpt_turn": False, "kpt_hidden": None}
"""What every checkpoint of the version before recorded in its config for the removed branches."""
OFF_TRAIN = {"kpt_turn": False, "kpt_hidden": None, "crop_split": False}


def _as_written_before(detector_checkpoint, path: Path, config: dict | None = None, train: dict | None = None) -> Path:
    """A tiny detector checkpoint whose config and train_config record the removed fields."""
    detector_checkpoint(path, 0)
    raw = torch.load(path, weights_only=True)
    raw["config"] = {**raw["config"], **OFF_CONFIG, **(config or {})}
    raw["train_config"] = {"dataset": "d", "out": "o", "imgsz": 64, **OFF_TRAIN, **(train or {})}
    raw["schema"] = 2
    save_checkpoint(path, raw)
    return path


def test_a_checkpoint_that_records_the_removed_branches_off_reads_without_them(detector_checkpoint, tmp_path):
    path = _as_written_before(detector_checkpoint, tmp_path / "old.pt")
    state = load_checkpoint(path)
    assert not set(OFF_CONFIG) & set(state["config"]) and not set(OFF_TRAIN) & set(state["train_config"])
    model, _ = load_model(path)
    assert model.head.kpt_channels == 27  # 24 corner values and the heading's 3, no turn logit


@pytest.mark.parametrize("part, field, value", [("config", "kpt_turn", True), ("config", "kpt_hidden", 48),
                                                ("train_config", "kpt_turn", True),
                                                ("train_config", "crop_split", True)])
def test_a_checkpoint_trained_with_a_removed_branch_is_refused_in_one_line_naming_the_file_and_field(
        detector_checkpoint, tmp_path, capsys, part, field, value):
    import numpy as np

    cv2 = pytest.importorskip("cv2", reason="opencv-python-headless is part of the train extra")

    from omnigen.cli import main

    path = _as_written_before(detector_checkpoint, tmp_path / "old.pt", **{"config" if part == "config" else "train":
                                                                           {field: value}})
    with pytest.raises(ValueError) as exc:
        load_checkpoint(path)
    said = str(exc.value)
    assert said.startswith(f"{path}: trained with {field}, a branch this version does not have") and "\n" not in said
    assert f"{part}.{field} is {value!r}" in said
    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "a.png"), np.zeros((32, 32, 3), np.uint8))
    assert main(["predict", str(path), str(tmp_path / "images"), "--out", str(tmp_path / "pred")]) == 1
    err = capsys.readouterr().err
    assert f"trained with {field}, a branch this version does not have" in err and "Traceback" not in err
