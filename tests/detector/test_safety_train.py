"""Issue 44, data safety of `omnigen train` and `omnigen train-crop`: a run folder is claimed (no
silent overwrite, no silently ignored --resume arguments), a kill between best.pt and last.pt
loses nothing, a non-finite loss stops the run before anything of it is saved, numeric options are
refused as they are parsed, and every checkpoint error is one line naming the file."""

from __future__ import annotations

import math
import pickle
import shutil
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("cv2", reason="opencv-python-headless is part of the train extra")

from omnigen.cli import main as omnigen
from omnigen.detector.training import train as train_module
from omnigen.detector.model.checkpoint import load_checkpoint, plain_branch, load_model, save_checkpoint
from omnigen.detector.training.crop_train import CropSet, new_stage, train_stage
from omnigen.detector.training.crop_train_config import CropTrainConfig
from omnigen.detector.data.samples import Augment, split_frames
from omnigen.detector.training.train import NonFiniteLoss, TrainConfig, train
from omnigen.detector.data.loader import EpochBatches

TINY = {"model": "n", "width": 0.125, "depth": 0.34}
# the design's plain branch (TrainConfig's defaults before the recipe, with AdamW): the trainer's
# mechanics, quickly; tests/detector/test_recipe.py trains the recipe itself
PLAIN = plain_branch()


def _run(dataset, out: Path, **settings) -> TrainConfig:
    """A tiny run of `dataset` (the shared split_fake_dataset: 9 train frames, so 3 steps an epoch)."""
    return TrainConfig(**{**PLAIN, "dataset": str(dataset.root), "out": str(out), "imgsz": 64, "epochs": 1, "batch": 3,
                          "workers": 0, "augment": asdict(Augment.off()), "warmup_iters": 2, "val_every": 0,
                          **TINY, **settings})


def _one_line(exc: pytest.ExceptionInfo, *names: object) -> str:
    text = str(exc.value)
    assert "\n" not in text and len(text) < 1000, text
    for name in names:
        assert str(name) in text, text
    return text


# -- hole 4: the run folder ---------------------------------------------------------------------

def test_a_run_folder_is_claimed_and_resume_refuses_other_settings(split_fake_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    train(_run(split_fake_dataset, run))
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    assert {"last.pt", "results.csv", "args.json"} <= set(before)

    # a new run into it, without --resume or --fresh: refused before anything is touched
    with pytest.raises(ValueError) as exc:
        train(_run(split_fake_dataset, run, lr0=0.1))
    assert "--resume" in _one_line(exc, run, "last.pt") and "--fresh" in str(exc.value)
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before

    # --resume with other settings (or another dataset): refused, each difference named as render names them
    other = tmp_path / "other-data"
    shutil.copytree(split_fake_dataset.root, other)
    with pytest.raises(ValueError) as exc:
        train(_run(split_fake_dataset, run, epochs=6, lr0=0.1), resume=True)
    _one_line(exc, "optim.lr0: 0.002 there, 0.1 now", "--epochs: 1 there, 6 now", run / "last.pt", run / "recipe.json")
    with pytest.raises(ValueError) as exc:
        train(TrainConfig(**{**asdict(_run(split_fake_dataset, run)), "dataset": str(other)}), resume=True)
    _one_line(exc, "DATASET:", str(other))
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before
    # where and how fast it runs may change
    train(_run(split_fake_dataset, run, workers=1, device="cpu"), resume=True)

    # the command line: --resume and --fresh exclude each other; a second run is refused in one line
    args = ["train", str(split_fake_dataset.root), "model.imgsz=64", "optim.batch=3", "--out", str(run), "--epochs",
            "1", "--workers", "0", "--val-every", "0"]
    with pytest.raises(SystemExit) as stop:
        omnigen(args + ["--resume", "--fresh"])
    assert stop.value.code == 2
    capsys.readouterr()
    assert omnigen(args) == 1
    assert "holds a training run" in capsys.readouterr().err


def test_fresh_deletes_only_a_runs_own_files_and_refuses_a_folder_with_others(split_fake_dataset, tmp_path):
    run = tmp_path / "run"
    train(_run(split_fake_dataset, run))
    (run / "notes.txt").write_text("mine")
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    with pytest.raises(ValueError) as exc:
        train(_run(split_fake_dataset, run), fresh=True)
    _one_line(exc, run, "notes.txt", "--fresh")
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before  # nothing deleted

    (run / "notes.txt").unlink()
    args = (run / "args.json").read_bytes()
    (run / "args.json").write_text('{"who": "someone else"}')  # a file of the run's name, not train's
    with pytest.raises(ValueError, match="args.json"):
        train(_run(split_fake_dataset, run), fresh=True)
    (run / "args.json").unlink()
    (run / "recipe.json").write_text('{"model": {"imgsz": 64}}')  # a user's recipe file, not train's mark
    with pytest.raises(ValueError, match="recipe.json: was not written by 'omnigen train'"):
        train(_run(split_fake_dataset, run), fresh=True)
    (run / "recipe.json").unlink()
    (run / "args.json").write_bytes(args)  # the run's own again: --fresh may delete it
    old = load_checkpoint(run / "last.pt")["model"]
    train(_run(split_fake_dataset, run, lr0=1e-2), fresh=True)
    new = load_checkpoint(run / "last.pt")
    assert new["train_config"]["lr0"] == 1e-2 and any(not torch.equal(old[k], new["model"][k]) for k in old)


def test_fresh_deletes_nothing_when_the_run_is_refused_and_never_someone_elses_weights(split_fake_dataset, tmp_path):
    """--fresh deleted the run before its inputs were checked: a missing dataset, a bad split or
    --weights RUN/last.pt left an empty folder; and any torch archive named last.pt passed as the
    run's own, so an Ultralytics weights/ folder was deleted by --fresh."""
    run = tmp_path / "run"
    train(_run(split_fake_dataset, run))
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    missing = replace(_run(split_fake_dataset, run), dataset=str(tmp_path / "no-such-dataset"))
    for broken in (missing, _run(split_fake_dataset, run, train_split="nope")):
        with pytest.raises(Exception):
            train(broken, fresh=True)
        assert {p.name: p.read_bytes() for p in run.iterdir()} == before
    with pytest.raises(ValueError, match="--weights .*which --fresh deletes"):
        train(_run(split_fake_dataset, run, weights=str(run / "last.pt")), fresh=True)
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before

    weights = tmp_path / "weights"  # another tool's run: torch archives named as ours, no args.json
    weights.mkdir()
    for name in ("best.pt", "last.pt"):
        torch.save({"model": {"w": torch.zeros(2)}}, weights / name)
    kept = {p.name: p.read_bytes() for p in weights.iterdir()}
    for fresh in (False, True):
        with pytest.raises(ValueError, match="no args.json of 'omnigen train'"):
            train(_run(split_fake_dataset, weights), fresh=fresh)
    assert {p.name: p.read_bytes() for p in weights.iterdir()} == kept


def test_a_folder_of_other_files_without_a_run_is_trained_into_beside_them(split_fake_dataset, tmp_path):
    # benchmarks/validate.py keeps its own markers in the run folder before training into it
    run = tmp_path / "run"
    run.mkdir()
    (run / "started").write_text("stamp\n")
    train(_run(split_fake_dataset, run))
    assert (run / "started").read_text() == "stamp\n" and (run / "last.pt").exists()


# -- hole 5: a kill between best.pt and last.pt ----------------------------------------------------

def test_best_pt_is_written_before_last_pt_and_given_back_on_resume(split_fake_dataset, tmp_path, monkeypatch):
    run = tmp_path / "run"
    order = []
    real_save = train_module.save_checkpoint

    def save(path, state):
        order.append(Path(path).name)
        real_save(path, state)

    monkeypatch.setattr(train_module, "save_checkpoint", save)
    cfg = _run(split_fake_dataset, run, val_every=1)
    train(cfg)
    assert order == ["best.pt", "last.pt"]  # a kill between them leaves a last.pt that re-does the epoch

    # as a kill between last.pt and best.pt left it before: last.pt records its epoch as the best,
    # best.pt lacks it, and the killed save's temporary file stays
    (run / "best.pt").unlink()
    (run / ".tmp-k1ll3d").write_bytes(b"\0" * 1000)
    train(cfg, resume=True)  # the run was finished: nothing to train, the folder tidied
    assert not list(run.glob(".tmp-*"))
    model, state = load_model(run / "best.pt")
    assert state["epoch"] == 0 and state["best_fitness"] == load_checkpoint(run / "last.pt")["best_fitness"]


def test_a_failed_save_leaves_no_temporary_file(tmp_path, monkeypatch):
    import omnigen.files as files

    def refuse(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(files.os, "replace", refuse)
    with pytest.raises(OSError):
        save_checkpoint(tmp_path / "last.pt", {"x": torch.zeros(3)})
    assert list(tmp_path.iterdir()) == []


# -- hole 2: a loss that is not finite ------------------------------------------------------------

def _nan_from(first: int):
    """learning_rate, NaN from iteration `first` on: weights that turn NaN in that step."""
    real = train_module.learning_rate
    return lambda cfg, it, total: math.nan if it >= first else real(cfg, it, total)


def test_a_non_finite_loss_stops_the_run_naming_epoch_step_and_frames(split_fake_dataset, tmp_path, monkeypatch):
    run = tmp_path / "run"
    cfg = _run(split_fake_dataset, run, epochs=3, save_interval=0.0)  # last.pt after every epoch
    monkeypatch.setattr(train_module, "learning_rate", _nan_from(3))  # epoch 2's first step: NaN weights
    with pytest.raises(NonFiniteLoss) as exc:
        train(cfg)
    # its second step is the first whose loss is NaN: named with the frames of its batch
    ids = split_frames(str(split_fake_dataset.root), "train")
    batch = [ids[i] for _, i in EpochBatches(len(ids), 3, cfg.seed).keys(1)[3:6]]
    _one_line(exc, "epoch 2, step 2 of 3", *batch, "holds epoch 1")
    state = load_checkpoint(run / "last.pt")
    assert state["epoch"] == 0 and all(torch.isfinite(v).all() for v in state["model"].values()
                                       if v.is_floating_point())

    # NaN weights made by an epoch's last step, which no loss of the epoch shows: nothing saved either
    monkeypatch.setattr(train_module, "learning_rate", _nan_from(2))
    with pytest.raises(NonFiniteLoss) as exc:
        train(_run(split_fake_dataset, tmp_path / "last-step", save_interval=0.0))
    _one_line(exc, "epoch 1, step 3 of 3", "nothing was saved")
    assert not (tmp_path / "last-step" / "last.pt").exists()


# -- hole 8: numeric options ------------------------------------------------------------------------

@pytest.mark.parametrize("option, value, said", [
    ("--epochs", "0", "outside [1, 100000]"), ("--time", "inf", "not a finite number"),
    ("--seed", "-1", "outside [0, 4294967295]"), ("--workers", "-1", "outside [0, 256]"),
    ("--val-every", "-1", "outside [0, 100000]"),
])
def test_train_refuses_numbers_out_of_range_as_it_parses_them(tmp_path, monkeypatch, capsys, option, value, said):
    monkeypatch.setattr(train_module, "train", lambda *a, **k: pytest.fail("training must not start"))
    with pytest.raises(SystemExit) as stop:
        omnigen(["train", str(tmp_path), "--out", str(tmp_path / "run"), option, value])
    assert stop.value.code == 2
    assert option in (err := capsys.readouterr().err) and said in err


@pytest.mark.parametrize("key, value, said", [
    ("optim.batch", "0", "outside [1, 4096]"), ("optim.lrf", "nan", "not a finite number"),
    ("optim.lr0", "0", "outside (0, 1]"), ("model.imgsz", "0", "outside [32, 8192]"),
    ("schedule.kpt_sigma_end", "0", "outside (0, 10]"), ("data.focus", "2", "outside [0, 1]"),
    ("crop_stage.steps", "-1", "outside [0, 10000000]"), ("model.imgsz", "64.0", "not a whole number"),
])
def test_train_refuses_recipe_values_out_of_range_in_one_line_naming_the_key(tmp_path, monkeypatch, capsys, key,
                                                                             value, said):
    monkeypatch.setattr(train_module, "train", lambda *a, **k: pytest.fail("training must not start"))
    assert omnigen(["train", str(tmp_path), f"{key}={value}", "--out", str(tmp_path / "run")]) == 1
    err = capsys.readouterr().err.strip()
    assert f"{key}: " in err and said in err and "\n" not in err


@pytest.mark.parametrize("option, value, said", [
    ("--steps", "0", "outside [1, 10000000]"), ("--batch", "0", "outside [1, 65536]"),
    ("--lr", "nan", "not a finite number"), ("--copies", "0", "outside [1, 1000]"),
    ("--balance", "1.5", "outside [0, 1]"), ("--threads", "-2", "outside [0, 1024]"),
    ("--heading-gain", "-1", "outside [0, 1000]"), ("--seed", "-1", "outside [0, "),
])
def test_train_crop_refuses_numbers_out_of_range_as_it_parses_them(tmp_path, capsys, option, value, said):
    with pytest.raises(SystemExit) as stop:
        omnigen(["train-crop", str(tmp_path), "--weights", str(tmp_path / "w.pt"), "--out", str(tmp_path / "c.pt"),
                 option, value])
    assert stop.value.code == 2
    assert option in (err := capsys.readouterr().err) and said in err


# -- hole 9: checkpoint errors ----------------------------------------------------------------------

def test_every_checkpoint_error_is_one_line_naming_the_file(detector_checkpoint, tmp_path, capsys):
    good = load_checkpoint(detector_checkpoint(tmp_path / "det.pt", 0))
    cases = {
        "five.pt": (5, "holds an int"),
        "tensor.pt": (torch.zeros(3), "holds a Tensor"),
        "no-classes.pt": ({k: v for k, v in good.items() if k != "classes"}, "lacks field 'classes'"),
        "list-config.pt": ({**good, "config": [1, 2]}, "config is a list"),
        "typed-config.pt": ({**good, "config": {**good["config"], "p2": "yes"}}, "config.p2 is 'yes', not of type bool"),
        "bad-model.pt": ({**good, "model": [torch.zeros(1)]}, "model is a list"),
        "bad-train-config.pt": ({**good, "train_config": {"imgsz": "big"}}, "train_config.imgsz is 'big'"),
    }
    for name, (state, said) in cases.items():
        torch.save(state, tmp_path / name)
        with pytest.raises(ValueError) as exc:
            load_model(tmp_path / name)
        _one_line(exc, tmp_path / name, said)

    # tensors of another model size: counted, not listed (load_state_dict's list is tens of kilobytes)
    other = tmp_path / "other-size.pt"
    torch.save({**good, "config": {**good["config"], "scale": "s", "width": None, "depth": None}}, other)
    with pytest.raises(ValueError) as exc:
        load_model(other)
    assert "have other shapes" in _one_line(exc, other)

    # a pickled Python object: refused without torch's advice to load it with weights_only=False
    with open(tmp_path / "object.pt", "wb") as fh:
        pickle.dump({"config": np.float64(1.0)}, fh)
    torch.save({**good, "x": np.float64(1.0)}, tmp_path / "numpy.pt")
    for name in ("object.pt", "numpy.pt"):
        with pytest.raises(ValueError) as exc:
            load_checkpoint(tmp_path / name)
        assert "weights_only" not in _one_line(exc, tmp_path / name)
    (tmp_path / "cut.pt").write_bytes((tmp_path / "det.pt").read_bytes()[:5000])
    with pytest.raises(ValueError) as exc:
        load_checkpoint(tmp_path / "cut.pt")
    _one_line(exc, tmp_path / "cut.pt", "not an omnigen checkpoint")

    # through a command: exit 1 and one line
    assert omnigen(["train-crop", str(tmp_path / "dataset"), "--weights", str(tmp_path / "five.pt"),
                    "--out", str(tmp_path / "crop.pt")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "five.pt" in err and "Traceback" not in err


def _crop_set(n: int = 8, size: int = 32) -> CropSet:
    """Crops that train_stage can draw from (their values do not matter here)."""
    return CropSet(crops=torch.zeros(n, 3, size, size, dtype=torch.uint8), corners=torch.zeros(n, 8, 2),
                   mask=torch.ones(n, 8, dtype=torch.bool), heading=torch.tensor([[1.0, 0.0, 0.0]]).repeat(n, 1),
                   cls=torch.arange(n) % 3, boxes=torch.tensor([[0.0, 0.0, 32.0, 32.0]]).repeat(n, 1),
                   true_area=torch.full((n,), 1024.0))


def test_a_damaged_train_crop_partial_state_is_one_line_naming_it(tmp_path):
    data, cfg = _crop_set(), CropTrainConfig(steps=4, batch=4)
    partial = tmp_path / "crop.pt.partial"
    train_stage(data, new_stage(32, 3, 0), cfg, partial=partial)  # a finished partial state
    good = torch.load(partial, weights_only=True)
    damaged = {
        "garbage": b"not a torch file",
        "cut": partial.read_bytes()[:3000],
        "five": 5,
        "no-net": {k: v for k, v in good.items() if k != "net"},
        "other-net": {**good, "net": new_stage(32, 3, 0, split=True).state_dict()},
        "bad-opt": {**good, "opt": {"state": {}, "param_groups": []}},
        "bad-rng": {**good, "rng": {"bit_generator": "nothing"}},
        "bad-step": {**good, "step": 99},
    }
    for name, content in damaged.items():
        if isinstance(content, bytes):
            partial.write_bytes(content)
        else:
            torch.save(content, partial)
        with pytest.raises(ValueError) as exc:
            train_stage(data, new_stage(32, 3, 0), cfg, partial=partial)
        _one_line(exc, partial)
