"""Issue 47, one recipe, one story: detector/recipe.py holds the validated recipe once; `omnigen train`
trains it end to end (the crop stage's second phase included, within --time), records it in
RUN/recipe.json, reruns or tweaks it (--recipe, KEY=VALUE), resumes either phase, and says what it
did in a short summary; nothing else re-declares a recipe value."""

from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
from dataclasses import asdict
from functools import partial
from pathlib import Path

import pytest
import torch

pytest.importorskip("cv2", reason="opencv-python-headless is part of the train extra")

from omnigen.cli import build_parser, main as omnigen  # noqa: E402
from omnigen.detector.training import crop_train
from omnigen.detector.training import time_budget  # noqa: E402
from omnigen.detector.training import train as train_module  # noqa: E402
from omnigen.detector.prediction import predict as predict_module  # noqa: E402
from omnigen.detector.prediction.predict import trained_vertical  # noqa: E402
from omnigen.detector.model.checkpoint import SCHEMA, load_checkpoint, load_model, save_checkpoint  # noqa: E402
from omnigen.detector.recipe import RECIPE, read_recipe, recipe_of, train_fields, with_overrides  # noqa: E402
from omnigen.detector.training.train import TrainConfig, train  # noqa: E402
from omnigen.detector.train_command import long_run_note, short_plan_note, summary_rows  # noqa: E402
from omnigen.outputs import json_made_by  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
TINY = {"model": "n", "width": 0.125, "depth": 0.34}
SMALL = ["model.imgsz=64", "optim.batch=3", "optim.warmup_iters=2", "crop_stage.side=32", "crop_stage.steps=6",
         "crop_stage.batch=4", "crop_stage.copies=1"]
"""The recipe at a size the fake dataset trains in seconds: its every part (windows off at this
input, repeat sampling, the heading, a crop stage with classes and its second phase) still on."""


def _recipe_run(dataset, out: Path, *keys: str, **settings) -> TrainConfig:
    """A TrainConfig of the recipe with SMALL and `keys`, a tiny model, as the command builds one."""
    return TrainConfig(**{**train_fields(with_overrides(RECIPE, [*SMALL, *keys])), "dataset": str(dataset.root),
                          "out": str(out), "epochs": 1, "workers": 0, "val_every": 1, **TINY, **settings})


def _crop_tensors(path: Path) -> dict[str, torch.Tensor]:
    return {k: v for k, v in load_checkpoint(path)["model"].items() if k.startswith("crop_net.")}


# -- one source of truth -------------------------------------------------------------------------------

PERTURB = r'''
import dataclasses, json, sys
sys.path.insert(0, sys.argv[1])
import omnigen.detector.recipe as r

def other(v):
    if isinstance(v, bool): return not v
    if isinstance(v, int): return v + 1
    if isinstance(v, float): return v + 0.125
    if isinstance(v, str): return v + "-other"
    if isinstance(v, tuple): return tuple(x + 0.125 for x in v)
    return {None: 7}.get(v, v)

def perturbed(obj):
    return dataclasses.replace(obj, **{f.name: perturbed(getattr(obj, f.name)) if dataclasses.is_dataclass(getattr(obj, f.name))
                                       else other(getattr(obj, f.name)) for f in dataclasses.fields(obj)})

r.RECIPE, r.RUN = perturbed(r.RECIPE), perturbed(r.RUN)
r.RUN = dataclasses.replace(r.RUN, device="meta", channels_last=True)
from omnigen.detector.training.train import TrainConfig
from omnigen.detector.training.crop_train_config import CropTrainConfig
from omnigen.cli import build_parser
from benchmarks.validate import build_parser as validate_parser

bad = []
def check(where, got, want):
    if got != want: bad.append(f"{where}: {got!r}, the recipe's {want!r}")

defaults = {f.name: f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
            for f in dataclasses.fields(TrainConfig) if f.name not in ("dataset", "out")}
for name, value in r.train_fields(r.RECIPE).items():
    check(f"TrainConfig.{name}", defaults[name], value)
for name in ("epochs", "time_minutes", "val_every", "workers", "device", "amp", "cache", "seed", "channels_last"):
    check(f"TrainConfig.{name}", defaults[name], getattr(r.RUN, name))
from omnigen.detector.data.samples import Augment
check("Augment()", dataclasses.asdict(Augment()), dataclasses.asdict(r.RECIPE.augment))
for f in dataclasses.fields(CropTrainConfig):
    want = r.RUN.seed if f.name == "seed" else getattr(r.RECIPE.crop_stage, f.name, None) if f.name != "amp" else "off"
    check(f"CropTrainConfig.{f.name}", getattr(CropTrainConfig(), f.name), want)
subs = next(a for a in build_parser()._actions if a.dest == "command").choices
train_opts = {a.dest: a.default for a in subs["train"]._actions}
for dest, name in (("epochs", "epochs"), ("time", "time_minutes"), ("val_every", "val_every"), ("device", "device"),
                   ("workers", "workers"), ("amp", "amp"), ("cache", "cache"), ("channels_last", "channels_last"),
                   ("seed", "seed")):
    check(f"train --{dest}", train_opts[dest], getattr(r.RUN, name))
crop_opts = {a.dest: a.default for a in subs["train-crop"]._actions}
for dest in ("steps", "batch", "lr", "copies", "balance", "heading_gain", "offset_gain", "split", "position"):
    check(f"train-crop --{dest}", crop_opts[dest], getattr(r.RECIPE.crop_stage, dest))
check("train-crop --seed", crop_opts["seed"], r.RUN.seed)
v = validate_parser().parse_args([])
check("validate --epochs", v.epochs, r.RUN.epochs)
print(json.dumps(bad))
'''


def test_no_command_config_or_benchmark_declares_a_recipe_value_of_its_own():
    """Every recipe value and run setting changed in detector/recipe.py before the rest is imported:
    TrainConfig's, data's Augment's and CropTrainConfig's defaults, train's and train-crop's options and validate's
    must all follow. A default written out again anywhere (even equal today) is caught here."""
    out = subprocess.run([sys.executable, "-c", PERTURB, str(ROOT)], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


RECIPE_FLAGS = ("--kpt-mode", "--kpt-l1", "--kpt-labelled", "--kpt-turn-start", "--kpt-turn", "--kpt-heading",
                "--kpt-hidden", "--kpt-sigma-end", "--heading-crop", "--heading-gain", "--crop-classes", "--crop-focus",
                "--repeat-thresh", "--crop-steps", "--crop-position", "--offset-gain", "--optimizer", "--lr0", "--vertical")


@pytest.mark.parametrize("script", ["validate.py", "gpu_validate.py", "bench_learning.py"])
def test_the_benchmarks_pass_train_no_recipe_flag(script):
    """They train `omnigen train`'s recipe, changed only by KEY=VALUE keys a user gives them."""
    text = (ROOT / "benchmarks" / script).read_text()
    said = [flag for flag in RECIPE_FLAGS if re.search(rf"[\"']{re.escape(flag)}[\"' ]", text)]
    assert not said, f"benchmarks/{script} passes recipe flags {said}"


def test_train_help_has_at_most_20_options_and_lists_the_recipe_keys(capsys):
    subs = next(a for a in build_parser()._actions if a.dest == "command").choices
    options = [a for a in subs["train"]._actions if a.option_strings]
    assert len(options) <= 20, [a.option_strings for a in options]
    text = subs["train"].format_help()
    assert "  loss.kpt_l1=2.0: " in text and "  crop_stage.steps=7000: " in text and "(default: 150)" in text


# -- keys and files ------------------------------------------------------------------------------------

def test_keys_and_recipe_files_are_checked_and_each_error_names_the_key_and_the_file(tmp_path):
    r = with_overrides(RECIPE, ["loss.kpt_l1=1.5", "augment.hsv=0,0,0", "model.p2=off", "data.window=0",
                                "crop_stage.side=32", "crop_stage.steps=5", "crop_stage.split=false"])
    assert (r.loss.kpt_l1, r.augment.hsv, r.model.p2, r.data.window) == (1.5, (0.0, 0.0, 0.0), False, 0)
    # TrainConfig holds it all (but predict's keys, which training does not read), args.json too
    cfg = asdict(TrainConfig(dataset="d", out="o", **train_fields(r)))
    assert recipe_of(cfg) == recipe_of(json.loads(json.dumps(cfg))) == r
    path = tmp_path / "r.json"
    for content, said in [('{"loss": {"kpt_l1": "2"}}', "loss.kpt_l1 is \"2\", not a number"),
                          ('{"model": {"imgsz": 640.0}}', "model.imgsz is 640.0, not a whole number"),
                          ('{"model": {"p2": 1}}', "model.p2 is 1, not true or false"),
                          ('{"crop_stage": {"sides": 64}}', "crop_stage.sides: no such recipe key"),
                          ('{"data": {"focus": 1.5}}', "data.focus: 1.5 is outside [0, 1]"),
                          ('[1]', "not a recipe"), ('{"loss": ', "not a JSON recipe")]:
        path.write_text(content)
        with pytest.raises(ValueError) as exc:
            read_recipe(path)
        assert str(exc.value).startswith(f"{path}: ") and said in str(exc.value) and "\n" not in str(exc.value)
    path.write_text('{"loss": {"kpt_l1": 0.5}}')  # a partial recipe: the rest is the validated one
    assert read_recipe(path) == with_overrides(RECIPE, ["loss.kpt_l1=0.5"])


def test_a_run_records_its_recipe_and_a_rerun_from_it_trains_the_same_first_epoch(split_fake_dataset, tmp_path,
                                                                                   capsys, monkeypatch):
    """RUN/recipe.json is the resolved recipe, marked as train's; `--recipe RUN/recipe.json` into
    another folder trains the same losses; keys given beside it change it. The run's best.pt and
    last.pt carry the crop stage of its second phase, which `omnigen predict RUN/best.pt` runs."""
    ds = str(split_fake_dataset.root)
    common = ["--epochs", "1", "--workers", "0", "--val-every", "1"]
    assert omnigen(["train", ds, *SMALL, "loss.kpt_l1=1.5", "predict.vertical=off", "--out", str(tmp_path / "a"),
                    *common]) == 0
    summary = capsys.readouterr().out
    recipe = tmp_path / "a" / "recipe.json"
    assert json_made_by("train")(recipe) and read_recipe(recipe).loss.kpt_l1 == 1.5
    assert read_recipe(recipe).predict.vertical == "off"
    assert omnigen(["train", ds, "--recipe", str(recipe), "--out", str(tmp_path / "b"), *common]) == 0
    assert (tmp_path / "b" / "recipe.json").read_text() == recipe.read_text()

    def losses(run: str) -> list[dict[str, str]]:
        rows = list(csv.DictReader((tmp_path / run / "results.csv").open()))
        return [{k: v for k, v in row.items() if k not in ("seconds", "time", "val_seconds")} for row in rows]
    assert losses("a") == losses("b") and float(losses("a")[0]["kpt_l1"]) > 0
    for name in ("best.pt", "last.pt"):
        state = load_checkpoint(tmp_path / "a" / name)
        assert state["crop_stage"]["by"] == "omnigen train" and state["crop_stage"]["steps_done"] == 6
        assert state["config"]["crop_split"] is True and state["config"]["crop_position"] is True
        assert state["crop_phase"] == "trained" and state["schema"] == SCHEMA
    model, _ = load_model(tmp_path / "a" / "best.pt")
    assert model.crop_net.position and torch.equal(model.state_dict()["crop_net.corners.out.weight"],
                                                   _crop_tensors(tmp_path / "a" / "last.pt")["crop_net.corners.out.weight"])
    assert not (tmp_path / "a" / train_module.CROP_PARTIAL).exists()
    told = []  # predict takes the run's predict.vertical (off) unless --vertical says otherwise
    monkeypatch.setattr(predict_module, "predict_images", lambda model, files, opts: told.append(opts.vertical) or [])
    for flags in ([], ["--vertical", "lines"]):
        assert omnigen(["predict", str(tmp_path / "a" / "best.pt"), str(split_fake_dataset.root / "images"),
                        "--out", str(tmp_path / "pred"), "--no-overlays", *flags]) == 0
    assert told == ["off", "lines"]
    # the summary: one time, the learning rate readably, only the loss parts that are on, no NaN
    assert "time (min)" in summary and "wall time" not in summary and "crop stage: steps" in summary
    assert "loss: kpt_l1" in summary and " nan" not in summary
    assert float(re.search(r"last learning rate\W+([\d.e+-]+)", summary).group(1)) > 0
    capsys.readouterr()
    args = build_parser().parse_args(["train", ds, "--recipe", str(recipe), "optim.lr0=0.01", "--out", "c"])
    from omnigen.detector.train_command import config_of

    cfg = config_of(args)
    assert (cfg.lr0, cfg.kpt_l1, cfg.imgsz) == (0.01, 1.5, 64)


# -- the second phase: resumed, time-boxed ------------------------------------------------------------

def test_a_run_killed_in_its_crop_phase_resumes_it_to_the_same_stage(split_fake_dataset, tmp_path, monkeypatch):
    monkeypatch.setattr(crop_train, "train_stage", partial(crop_train.train_stage, save_interval=0.0))
    train(_recipe_run(split_fake_dataset, tmp_path / "full"))
    real_progress = crop_train.stage_progress

    def killed_at_step_3(steps, label):
        report = real_progress(steps, label)

        def step(n, parts):
            report(n, parts)
            if n == 3:
                raise KeyboardInterrupt  # as a kill would: the partial state of step 3 is saved
        return step
    monkeypatch.setattr(crop_train, "stage_progress", killed_at_step_3)
    cut = tmp_path / "cut"
    with pytest.raises(KeyboardInterrupt):
        train(_recipe_run(split_fake_dataset, cut))
    monkeypatch.setattr(crop_train, "stage_progress", real_progress)
    assert (cut / train_module.CROP_PARTIAL).exists() and "crop_phase" not in load_checkpoint(cut / "last.pt")
    # the detector's phase was done: --resume goes on with the crop phase, from its step 3
    with pytest.raises(ValueError, match=r"crop_stage\.steps: 6 there, 7 now; .*recipe\.json: --recipe"):
        train(_recipe_run(split_fake_dataset, cut, "crop_stage.steps=7"), resume=True)
    last = train(_recipe_run(split_fake_dataset, cut), resume=True)
    assert last["crop_steps"] == 6 and not (cut / train_module.CROP_PARTIAL).exists()
    full, resumed = _crop_tensors(tmp_path / "full" / "last.pt"), _crop_tensors(cut / "last.pt")
    for k in full:
        torch.testing.assert_close(resumed[k], full[k], rtol=0, atol=0, msg=k)
    # finished: a resume has nothing to do, and says what the run did
    again = train(_recipe_run(split_fake_dataset, cut), resume=True)
    assert again["crop_steps"] == 6 and again["epoch"] == 1


@pytest.fixture
def fake_clock(monkeypatch):
    """A deterministic clock: a detector step takes 0.5 s, a validation 2 s, a crop-stage step 0.1 s."""
    now = [0.0]
    monkeypatch.setattr(time_budget, "clock", lambda: now[0])
    real_to_device, real_validate, real_loss = train_module.to_device, train_module.validate, crop_train.stage_loss

    def advance(seconds, real):
        def call(*args, **kw):
            now[0] += seconds
            return real(*args, **kw)
        return call
    monkeypatch.setattr(train_module, "to_device", advance(0.5, real_to_device))
    monkeypatch.setattr(train_module, "validate", advance(2.0, real_validate))
    monkeypatch.setattr(crop_train, "stage_loss", advance(0.1, real_loss))
    return now


def test_a_time_budget_keeps_a_share_for_the_crop_phase_and_fits_its_steps_to_what_is_left(
        split_fake_dataset, tmp_path, fake_clock, capsys):
    # 40 s: the detector plans its epochs in 32 s (epochs of 4 steps, 2 s, and a 2 s validation kept
    # for the end); the crop phase then has what is left: its 200 steps of 0.1 s do not fit, the
    # steps that do are trained (the 5 steps timed first counted)
    last = train(_recipe_run(split_fake_dataset, tmp_path / "run", "crop_stage.steps=200",
                             epochs=1000, time_minutes=40 / 60))
    state = load_checkpoint(tmp_path / "run" / "last.pt")
    detector_time = state["history"][-1]["time"]
    assert detector_time <= 32.0 + 2.0  # an overrun of at most its last epoch
    steps = state["crop_stage"]["steps_done"]
    assert abs(steps - (40.0 - detector_time - 5 * 0.1) / 0.1) <= 1 and 20 <= steps < 200
    assert state["crop_stage"]["config"]["steps"] == steps == last["crop_steps"]
    assert fake_clock[0] <= 40.0 + 1e-6
    assert "the crop phase's 200 steps take 0.3 min" in capsys.readouterr().err
    # a budget that leaves less than a tenth of the steps: the stage trained with the detector is kept
    train(_recipe_run(split_fake_dataset, tmp_path / "short", "crop_stage.steps=200", epochs=1000,
                      time_minutes=10 / 60))
    state = load_checkpoint(tmp_path / "short" / "last.pt")
    assert "crop_stage" not in state and state["crop_phase"].startswith("too few of the crop phase's 200 steps")
    assert state["config"]["crop_position"] is False  # the joint stage, as trained with the detector


def test_the_budget_rules():
    assert time_budget.detector_seconds(125.0, True) == 6000.0 and time_budget.detector_seconds(125.0, False) == 7500.0
    assert time_budget.fit_steps(7000, 0.1, 1e6) == 7000  # they fit: the recipe's
    assert time_budget.fit_steps(7000, 0.1, 350.0) == 3500
    assert time_budget.fit_steps(7000, 0.1, 69.0) == 0  # under a tenth: none
    assert time_budget.fit_steps(40, 0.1, -5.0) == 0


# -- checkpoints of before -------------------------------------------------------------------------------

def test_a_checkpoint_from_before_the_schema_reads_as_what_it_was_trained_with(detector_checkpoint, tmp_path):
    path = detector_checkpoint(tmp_path / "old.pt", 0)  # saved as train saved one before: no schema
    raw = torch.load(path, weights_only=True)
    save_checkpoint(path, {**raw, "train_config": {"dataset": "d", "out": "o", "imgsz": 64}})  # fields of then
    state = load_checkpoint(path)
    assert state["schema"] == SCHEMA and state["train_config"]["imgsz"] == 64
    assert state["train_config"]["kpt_mode"] == "anchor" and state["train_config"]["kpt_heading"] is False
    assert state["train_config"]["crop_phase"] == {"steps": 0}  # no second phase then
    assert load_model(path)[0].cfg.heading_crop == 0  # predict and eval read it as before
    assert trained_vertical(state) == RECIPE.predict.vertical  # no predict section then: the recipe's
    save_checkpoint(path, {**raw, "train_config": {"dataset": "d", "out": "o", "predict": {"vertical": "up"}}})
    with pytest.raises(ValueError) as exc:
        load_model(path)
    assert str(exc.value).startswith(f"{path}: train_config.predict: predict.vertical: 'up' is not one of")
    raw["schema"] = SCHEMA + 1
    save_checkpoint(tmp_path / "new.pt", raw)
    with pytest.raises(ValueError) as exc:
        load_checkpoint(tmp_path / "new.pt")
    assert str(exc.value).startswith(f"{tmp_path / 'new.pt'}: schema is {SCHEMA + 1}")


# -- what the user is told ---------------------------------------------------------------------------------

def test_the_summary_shows_the_parts_that_are_on_one_time_and_no_nan():
    # heading_crop and crop_cls off (0 throughout), crop_corners not finite: left out
    last = {"epoch": 150, "lr": 2e-05, "seconds": 35.8, "box": 1.2, "dfl": 0.9, "cls": 0.8, "kpt": 0.5, "kvis": 0.3,
            "kpt_l1": 0.4, "kpt_labelled": 0.2, "heading": 0.1, "heading_crop": 0.0, "crop_cls": 0.0,
            "crop_corners": float("nan"), "oks_map50_95": 0.1, "corner_error_px": float("nan"), "time": 5686.6,
            "crop_seconds": 995.4, "crop_steps": 7000, "crop_corner_rel": 0.155}
    rows = dict(summary_rows(last, 35.8, 10.0))
    assert rows["last learning rate"] == "2e-05" and rows["time (min)"] == "111.4"  # detector and crop phase
    assert [k for k in rows if k.startswith("loss: ")] == [
        f"loss: {k}" for k in ("box", "dfl", "cls", "kpt", "kvis", "kpt_l1", "kpt_labelled", "heading")]
    assert "corner error (px)" not in rows and rows["OKS mAP50:95"] == "0.100" and rows["crop stage: steps"] == "7000"
    assert [k for k in rows if "time" in k] == ["time (min)"]


def test_a_long_run_is_told_after_its_first_epoch_and_pointed_at_time():
    note = long_run_note(36.0, 149, 10)
    assert "1.5 h" in note and "--time MINUTES" in note
    assert long_run_note(2.0, 149, 10) is None


def test_a_time_box_that_fits_fewer_epochs_than_asked_says_so_after_the_first():
    note = short_plan_note(125.0, 48.4, 116, 150)
    assert note.startswith("--time 125: an epoch took 48 s, so about 116 of the 150 epochs fit") and "shorter" in note
    assert short_plan_note(125.0, 35.8, 150, 150) is None


