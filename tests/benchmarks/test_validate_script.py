"""benchmarks/validate.py and the stages it shares with gpu_validate.py (benchmarks/common.py): what a
done-marker means, which records a redo drops, what RESULTS.md shows."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import shutil  # noqa: E402

import pytest  # noqa: E402

import benchmarks.validate as validate  # noqa: E402
from benchmarks.common import (Runner, check_data_arguments, mentions, stale, train_stage, train_stamp,  # noqa: E402
                               trains_into)
from benchmarks.validate import command_line, curve_table, results_markdown, size_table, validated_on  # noqa: E402


def test_mentions_names_a_folder_and_its_files_not_its_siblings():
    run = Path("runs/v/runs/n-p2")
    assert mentions("omnigen train uov --out runs/v/runs/n-p2 --epochs 60", run)
    assert mentions("omnigen eval runs/v/runs/n-p2/test-predictions.json uov", run)
    assert mentions("predict_dataset(runs/v/runs/n-p2, uov)", run)
    assert mentions("omnigen train uov --out runs/v/runs/n-p2", run)
    assert not mentions("omnigen train uov --out runs/v/runs/n-p2-480 --epochs 60", run)
    assert not mentions("omnigen train uov --out runs/v/runs/n-p2x", run)


def test_a_marker_from_other_arguments_is_stale(tmp_path):
    marker = tmp_path / "done"
    assert not stale(marker, "train --epochs 60")  # no marker: nothing to redo, nothing done
    marker.write_text("train --epochs 30\n")
    assert stale(marker, "train --epochs 60")
    marker.write_text("train --epochs 60\n")
    assert not stale(marker, "train --epochs 60")


def test_a_run_trained_without_the_image_cache_is_not_redone_with_it(tmp_path):
    # the cache changes the speed, not the weights: the marker of a run without it still stands
    marker = tmp_path / "done"
    marker.write_text("train uov --out runs/n-p2 --epochs 60\n")
    assert not stale(marker, train_stamp("train uov --out runs/n-p2 --epochs 60 --cache"))
    assert stale(marker, train_stamp("train uov --out runs/n-p2 --epochs 90 --cache"))
    run = Runner(tmp_path)
    run.record("omnigen train uov --out runs/n-p2 --epochs 60", 30.0)
    run.record("omnigen train uov --out runs/n-p2-960 --epochs 60 --cache", 50.0)
    assert run.seconds("omnigen train uov --out runs/n-p2 --epochs 60 --cache") == 30.0
    assert run.seconds("omnigen train uov --out runs/n-p2-960 --epochs 60") == 50.0


def test_a_command_run_again_replaces_its_record(tmp_path):
    run = Runner(tmp_path)
    run.record("omnigen eval p.json uov --out runs/n-p2/eval.json", 9.0)
    run.record("omnigen train uov --out runs/n-p2", 60.0)
    run.record("omnigen eval p.json uov --out runs/n-p2/eval.json", 12.0)  # eval.json deleted, evaluated again
    assert [c["seconds"] for c in Runner(tmp_path).log] == [60.0, 12.0]


def test_a_command_run_here_records_its_cpu_share_and_the_load(tmp_path, monkeypatch):
    """A reader of RESULTS.md sees whether a stage had the machine to itself: an in-process command
    that burns CPU for its whole wall time on one of two usable cores reads a share of at most 0.5."""
    import benchmarks.common as common

    def busy(argv):
        end = time.process_time() + 0.3
        while time.process_time() < end:
            pass
        return 0

    monkeypatch.setattr(common, "usable_cores", lambda: 2)
    monkeypatch.setattr(common.os, "getloadavg", lambda: (3.456, 0.0, 0.0))
    run = Runner(tmp_path)
    run.omnigen = busy
    run(["eval", "p.json", "uov"])
    entry = Runner(tmp_path).log[-1]
    assert entry["load"] == 3.46 and 0 < entry["cpu_share"] <= 0.55  # one thread of two cores; less when shared
    run.record("omnigen render --rig ego", 5.0)  # a subprocess's: the load alone
    assert "cpu_share" not in Runner(tmp_path).log[-1] and Runner(tmp_path).log[-1]["load"] == 3.46
    run.record("omnigen train uov --out runs/n-p2", 600.0, now=False)  # recovered from its results.csv
    assert "load" not in Runner(tmp_path).log[-1]


class FakeTrain:
    """Stands in for `omnigen train`: writes a checkpoint whose epochs took 40 s and, while `kill` is
    set, dies after it as a killed job would."""

    def __init__(self) -> None:
        self.calls: list[list[str]] = []
        self.kill = False

    def __call__(self, argv: list[str]) -> int:
        self.calls.append(argv)
        out = Path(argv[argv.index("--out") + 1])
        (out / "last.pt").write_bytes(b"checkpoint")
        (out / "results.csv").write_text("epoch,seconds,time\n1,20,20\n2,20,40\n")
        if self.kill:
            raise KeyboardInterrupt
        return 0


def test_a_training_cut_off_midway_goes_on_from_its_checkpoint_and_counts_its_time(tmp_path, monkeypatch):
    fake = FakeTrain()
    monkeypatch.setattr(Runner, "omnigen", staticmethod(fake))
    run, out = Runner(tmp_path), tmp_path / "runs" / "s-p2"
    cmd = ["train", "uov", "--out", str(out), "--epochs", "150"]
    fake.kill = True
    with pytest.raises(KeyboardInterrupt):
        train_stage(run, cmd, out)
    assert not (out / "done").exists() and run.log == []  # nothing recorded for the killed invocation
    fake.kill = False
    seconds = train_stage(run, [*cmd, "--cache"], out)  # the cache changes no weights: the same run
    assert fake.calls[-1] == [*cmd, "--cache", "--resume"]
    assert 40.0 <= seconds < 45.0  # the 40 s before the kill, plus this invocation's
    assert [c["command"] for c in run.log] == ["omnigen " + " ".join(cmd) + " --cache"]
    assert train_stage(run, cmd, out) == seconds and len(fake.calls) == 2  # done: skipped, same seconds


def test_a_trained_folder_moved_back_is_reported_as_its_own_training(tmp_path, monkeypatch):
    """A run folder put back by hand after another training wrote into it (and was recorded): the
    log drops that other training and records this one with its epochs' seconds, so RESULTS.md
    neither lists a training that is not there nor a train time of 0."""
    fake = FakeTrain()
    monkeypatch.setattr(Runner, "omnigen", staticmethod(fake))
    run, out = Runner(tmp_path), tmp_path / "runs" / "n-p2"
    cmd = ["train", "uov", "--out", str(out), "--imgsz", "640"]
    train_stage(run, cmd, out)
    kept = out.with_name("kept")
    out.rename(kept)
    train_stage(run, ["train", "uov", "--out", str(out), "--imgsz", "960"], out)
    shutil.rmtree(out)
    kept.rename(out)  # the 640 run back
    run.record("omnigen render --out elsewhere", 3.0)
    assert train_stage(run, cmd, out) == 40.0 and len(fake.calls) == 2  # skipped: done
    assert [c["command"] for c in Runner(tmp_path).log] == ["omnigen render --out elsewhere",
                                                             "omnigen " + " ".join(cmd)]


def test_a_training_cut_off_with_other_arguments_starts_over(tmp_path, monkeypatch):
    fake = FakeTrain()
    monkeypatch.setattr(Runner, "omnigen", staticmethod(fake))
    run, out = Runner(tmp_path), tmp_path / "runs" / "n-p2"
    fake.kill = True
    with pytest.raises(KeyboardInterrupt):
        train_stage(run, ["train", "uov", "--out", str(out), "--epochs", "150"], out)
    (out / "stray").write_text("from the cut-off run")
    fake.kill = False
    train_stage(run, ["train", "uov", "--out", str(out), "--epochs", "100"], out)
    assert "--resume" not in fake.calls[-1] and not (out / "stray").exists()
    assert (out / "started").read_text() == (out / "done").read_text()


def test_a_folder_rendered_with_other_data_arguments_is_refused(tmp_path):
    args = argparse.Namespace(frames=200, cities=5, size=640, backend="raster", seed=0, scene="downtown,suburban",
                              kitti=Path("../shared/realdata/kitti"), dair=None, epochs=150)
    names = validate.DATA_ARGUMENTS
    check_data_arguments(tmp_path, args, names)  # first run: recorded
    check_data_arguments(tmp_path, argparse.Namespace(**{**vars(args), "epochs": 30}), names)  # training may change
    with pytest.raises(SystemExit, match=r"--size 640 \(now 320\).*--fresh"):
        check_data_arguments(tmp_path, argparse.Namespace(**{**vars(args), "size": 320}), names)


def test_forget_drops_only_the_redone_folder(tmp_path):
    run = Runner(tmp_path)
    run.record("omnigen train uov --out w/runs/n-p2 --epochs 30", 10.0)
    run.record("omnigen train uov --out w/runs/n-p2-480 --epochs 30", 20.0)
    run.record("omnigen eval w/runs/n-p2/test-predictions.json uov", 1.0)
    run.forget(Path("w/runs/n-p2"))
    assert [c["command"] for c in run.log] == ["omnigen train uov --out w/runs/n-p2-480 --epochs 30"]
    assert Runner(tmp_path).log == run.log  # the log on disk says the same


def test_object_sizes_per_view_of_a_split(tmp_path):
    import numpy as np

    from benchmarks.validate import object_sizes
    from omnigen.fakes import write_fake_dataset
    from omnigen.splits import write_split

    ds = write_fake_dataset(tmp_path / "ds", n_frames=6, seed=3)
    test = ds.frame_ids[:3]
    write_split(ds.root, "test", test)
    sizes = object_sizes(ds, "test")
    rows = [ds.index_of(f) for f in test]
    o = ds.objects
    keep = np.isin(o.frame, rows)
    assert sum(v["objects"] for v in sizes.values()) == int(keep.sum())
    for view, v in sizes.items():
        assert v["p10_px"] <= v["p50_px"] <= v["p90_px"] and v["p50_m"] > 0


def test_results_markdown_names_the_command_and_every_class_row():
    row = {"oks_map50_95": 0.25, "ap_oks50": 0.5, "f1": 0.4, "ground_adherence_deg": 2.0, "precision": 0.5,
           "recall": 0.3, "objects": 7}
    r = {"arguments": {"kitti": "../shared/realdata/kitti", "epochs": 3, "jobs": 2, "scales": ["n"], "ablations": [],
                       "fresh": False, "amp": None},
         "machine": "x86_64, 2 CPUs", "date": "2026-11-21 12:00 UTC", "wall_seconds": 120.0,
         "frames": {"total": 10, "by_source": {"synthetic": 9, "kitti": 1}, "objects": 50, "splits": None},
         "oks_map50_95": 0.25, "ap_oks50": 0.5, "precision": 0.5, "recall": 0.3, "f1": 0.4, "bev_adherence_deg": 2.0,
         "targets": {"oks_map50_95": 0.55, "bev_adherence_deg": 3.57},
         "test_object_sizes": {"ego": {"objects": 7, "p10_px": 5.0, "p50_px": 9.0, "p90_px": 20.0, "p50_m": 17.5}},
         "by_view": [{**row, "group": "view=ego"}],
         "by_class": [{**row, "group": "class=car"}, {**row, "group": "class=motorcyclist", "oks_map50_95": 0.0}],
         "runs": [{"name": "n-p2", "train_args": ["--model", "n"], "imgsz": 640, "crop": 320, "train_seconds": 60.0,
                   "median_epoch_seconds": 0.4,
                   "synthetic_test": row, "overall_test": row,
                   "corner_order": {"matched": 10, "unmatched": 2, "best": {"as labelled": 6, "turned 180": 4, "mirrored": 0,
                                                                           "turned +90": 0, "turned -90": 0}}}],
         "commands": [{"command": "omnigen merge a --out b", "seconds": 1.5}]}
    md = results_markdown(r)
    # the options that differ from the script's defaults (jobs 2 and scales n are its defaults)
    assert "`python benchmarks/validate.py --kitti ../shared/realdata/kitti --epochs 3` (every other option at its default" in md
    assert "| car | 7 | 0.250 | 0.500 | 0.500 | 0.300 | 0.400 |" in md
    assert "| motorcyclist | 7 | 0.000 |" in md
    assert "| ego | 0.250 | 0.500 | 0.400 | 2.00 (0) | 7 | 5.0 / 9.0 / 20.0 | 17.5 |" in md
    assert "| n-p2 | `--model n` | 640 (320) | 60.0 | 0.4 | 0.250 |" in md
    assert "| n-p2 | 10 | 2 | 6 (60%) | 4 (40%) | 0 (0%) | 0 (0%) | 0 (0%) |" in md
    # the command is said once, at the top, not under each of the six tables (issue 47)
    tables = sum(line.startswith("|---") for line in md.splitlines())
    assert tables == 6 and md.count("python benchmarks/validate.py --kitti") == 1 and "Made by" not in md
    assert "upsampled" not in md  # no run's input exceeds the renders
    assert "share of the input" not in md  # one run: no windows to compare
    assert "By object size" not in md  # no run has size rows


def test_results_markdown_shows_what_the_truths_own_corners_score():
    from benchmarks.validate import floor_table

    rows = [{"noise_px": n, "group": g, "oks_map50_95": m, "adherence_deg": a, "adherence_objects": 5, "lift_failures": 0}
            for n, g, m, a in [(0.0, "source=synthetic", 0.99, 0.78), (0.0, "view=aerial", 1.0, 1.28),
                               (2.0, "source=synthetic", 0.54, 4.63), (2.0, "view=aerial", 0.5, 6.74)]]
    lines = floor_table({"adherence_floor": rows})
    assert "| noise (px) | synthetic | aerial |" in lines
    assert "| 0 | 0.990 / 0.78 | 1.000 / 1.28 |" in lines and "| 2 | 0.540 / 4.63 | 0.500 / 6.74 |" in lines
    assert "Made by" not in "\n".join(lines)
    assert floor_table({}) == []  # results.json from before the floor rows


def test_results_markdown_compares_every_run_by_object_size():
    def row(group, m, objects):
        return {"group": group, "oks_map50_95": m, "ap_oks50": 2 * m, "objects": objects}

    bins = {"tiny": [0.0, 16.0], "small": [16.0, 32.0], "large": [96.0, 1e5]}
    runs = [{"name": "n-p2", "report_rows": [row("overall", 0.2, 9), row("size=tiny", 0.1, 5), row("size=large", 0.3, 4)]},
            {"name": "n-no-p2", "report_rows": [row("size=tiny", 0.05, 5), row("size=large", 0.4, 4)]},
            {"name": "n-p2-no-synthetic", "report_rows": []}]
    lines = size_table({"size_bins_px": bins, "runs": runs})
    assert "| run | tiny: < 16 px (5 objects) | large: >= 96 px (4 objects) |" in lines  # no small objects: no column
    assert "| n-p2 | 0.100 / 0.200 | 0.300 / 0.600 |" in lines
    assert "| n-no-p2 | 0.050 / 0.100 | 0.400 / 0.800 |" in lines
    assert "| n-p2-no-synthetic | - | - |" in lines
    assert size_table({"runs": runs}) == []  # results.json from before the size rows
    # read back from results.json, whose keys are sorted (large before tiny): still smallest first
    assert size_table({"size_bins_px": dict(sorted(bins.items())), "runs": runs}) == lines


def test_results_markdown_says_a_larger_input_is_upsampled_and_its_training_windows_hold_less():
    row = {"oks_map50_95": 0.1, "ap_oks50": 0.2, "f1": 0.3, "ground_adherence_deg": None}
    runs = [{"name": name, "train_args": [], "imgsz": imgsz, "crop": 320, "train_seconds": 1.0,
             "synthetic_test": row, "overall_test": row} for name, imgsz in (("n-p2", 640), ("n-p2-960", 960))]
    r = {"arguments": {"size": 640, "jobs": 2, "scales": ["n"], "ablations": ["hires"]}, "machine": "m", "date": "d",
         "wall_seconds": 60.0, "frames": {"total": 1, "by_source": {}, "objects": 1, "splits": None},
         "oks_map50_95": 0.1, "ap_oks50": 0.2, "precision": 0.3, "recall": 0.3, "f1": 0.3, "bev_adherence_deg": None,
         "targets": {"oks_map50_95": 0.55, "bev_adherence_deg": 3.57}, "test_object_sizes": {}, "runs": runs,
         "commands": []}
    md = results_markdown(r)
    assert "rendered at 640 x 640; n-p2-960 letterboxed them" in md and "| n-p2-960 | the recipe | 960 (320) | 1.0 | - |" in md
    # the same 320 window holds a quarter of the 640 input, a ninth of the 960 one
    assert "the share of the input a window holds: n-p2: 25%; n-p2-960: 11%." in md
    for run in runs:
        run["crop"] = None  # whole images: nothing to say
    assert "share of the input" not in results_markdown(r)


def test_results_markdown_shows_how_the_test_score_grew_in_the_runs_that_validated_on_it():
    def curve(*maps):
        return [{"epoch": 10 * (i + 1), "oks_map50_95": m, "ap_oks50": 2 * m} for i, m in enumerate(maps)]

    runs = [{"name": "n-p2", "curve": curve(0.01, 0.02, 0.025), "validated_on": "test"},
            {"name": "n-no-p2", "curve": curve(0.01, 0.03), "validated_on": "test"},
            {"name": "n-p2-no-synthetic", "curve": curve(0.0, 0.0, 0.0), "validated_on": "train"}]
    lines = curve_table({"runs": runs})
    assert "| epoch | n-p2 | n-no-p2 |" in lines  # the run validated on its train split has no column
    assert "| 10 | 0.010 / 0.020 | 0.010 / 0.020 |" in lines
    assert "| 30 | 0.025 / 0.050 | - |" in lines  # a shorter history leaves its cell empty
    assert any("Left out: n-p2-no-synthetic" in line for line in lines)
    assert curve_table({"runs": [{"name": "n-p2"}]}) == []  # results.json from before the curves


def test_a_run_is_said_to_validate_on_the_split_train_picks(tmp_path):
    from omnigen.fakes import write_fake_dataset
    from omnigen.splits import write_split

    merged, real = (write_fake_dataset(tmp_path / name, n_frames=4, seed=3) for name in ("uov", "uov-real"))
    write_split(merged.root, "test", merged.frame_ids[:1])
    assert validated_on(merged.root, ["--model", "n"], merged.root) == "test"  # no val split: test
    write_split(merged.root, "val", merged.frame_ids[1:2])
    assert validated_on(merged.root, ["--model", "n"], merged.root) == "val"
    assert validated_on(real.root, ["--model", "n", "--val-split", "train"], merged.root) == "train of uov-real"
    assert validated_on(real.root, ["--model", "n"], merged.root) == "all of uov-real"  # no splits at all


def test_results_markdown_puts_the_model_beside_the_box_template_baseline():
    from benchmarks.validate import baseline_table

    r = {"oks_map50_95": 0.12, "ap_oks50": 0.3, "bev_adherence_deg": 4.5, "corner_error_px": 3.25,
         "corner_error_rel": 0.081,
         "baseline": {"oks_map50_95": 0.02, "ap_oks50": 0.06, "ground_adherence_deg": None, "corner_error_px": 7.5,
                      "corner_error_rel": 0.2}}
    md = "\n".join(baseline_table(r))
    assert "| OKS mAP50:95 | 0.120 | 0.020 |" in md
    assert "| ground-plane adherence (deg) | 4.50 | - |" in md
    assert "| the same, relative to sqrt(box area) | 0.081 | 0.200 |" in md and "Made by" not in md
    assert baseline_table({"oks_map50_95": 0.1}) == []  # results from before the baseline


def test_data_only_stops_at_the_merged_dataset(tmp_path, monkeypatch):
    """--data-only renders (here: renders already done), merges and stops: no training command."""
    calls: list[list[str]] = []

    def fake(argv: list[str]) -> int:
        calls.append(argv)
        out = Path(argv[argv.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        (out / "manifest.json").write_text("{}")
        return 0

    monkeypatch.setattr(Runner, "omnigen", staticmethod(fake))
    for folder in ("render-ego-s0", "render-pole-s100", "render-drone-s200"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "manifest.json").write_text("{}")
    assert validate.main(["--work", str(tmp_path), "--frames", "2", "--cities", "1", "--data-only"]) == 0
    assert [c[0] for c in calls] == ["merge"]


VALIDATED_TRAIN_CONFIG = {
    # TrainConfig as docs/RESULTS.md's make validate resolved it from its 24 `omnigen train` flags
    # (docs/results.json, the command of runs/validate/runs/n-p2), before the recipe was train's own
    "model": "n", "backbone": "c3k2", "p2": True, "p6": False, "width": None, "depth": None, "imgsz": 640, "crop": 320,
    "crop_focus": 0.5, "repeat_thresh": 0.3, "cache": True, "epochs": 150, "batch": 16, "optimizer": "adamw",
    "lr0": 0.002, "lrf": 0.01, "weight_decay": 5e-4, "warmup_iters": 100, "ema_decay": 0.9999, "ema_tau": 2000.0,
    "kpt_sigma_start": 0.5, "kpt_sigma_anneal": 0.3, "kpt_sigma_end": 0.25, "kpt_mode": "box", "kpt_l1": 2.0,
    "kpt_labelled": 1.0, "kpt_turn_start": 0.3, "kpt_heading": True,
    "heading_gain": 1.0, "heading_crop": 64, "crop_classes": True, "taxonomy": "fine",
    "train_split": "train", "val_split": None, "out_of_image": "learn",
    "augment": {"flip": 0.5, "scale": 0.5, "translate": 0.1, "hsv": (0.015, 0.7, 0.4)}, "predict": {"vertical": "lines"},
    # the loader's workers and the image cache change the speed, not the weights: validate now
    # leaves the workers to train (none on 2 cores) and keeps the images in memory
    "workers": None, "seed": 0,
    "val_every": 50, "save_interval": 60.0, "device": None, "amp": "bf16", "channels_last": None, "weights": None}
VALIDATED_CROP_STAGE = {
    # `omnigen train-crop ... --steps 7000 --seed 0 --amp bf16 --position --offset-gain 0.3` with its
    # defaults then: what the crop stage of docs/RESULTS.md was trained with
    "config": {"steps": 7000, "batch": 64, "lr": 2e-3, "weight_decay": 1e-4, "copies": 4, "balance": 0.0,
               "heading_gain": 0.1, "class_gain": 0.5, "offset_gain": 0.3, "seed": 0, "amp": "bf16"},
    "crop": 64, "classes": True, "split": True, "position": True}


def test_make_validate_trains_exactly_the_validated_model_from_train_s_own_recipe():
    """Issue 47: validate passes `omnigen train` the data and the budget only; what train resolves
    from that command line is the TrainConfig of docs/RESULTS.md's run (its 100 minutes for the
    detector) and, for the second phase, train-crop's settings of that run."""
    from dataclasses import asdict

    from omnigen.cli import build_parser
    from omnigen.detector.training.crop_train import stage_config
    from omnigen.detector.training.time_budget import detector_seconds
    from omnigen.detector.training.train import crop_phase_due
    from omnigen.detector.train_command import config_of

    ap = validate.build_parser()
    args = ap.parse_args(["--work", "runs/validate"])
    args.amp = "bf16"  # default_amp's choice on the 2-core CPU that runs bfloat16 natively
    argv = validate.train_command(args, Path("runs/validate/uov"), Path("runs/validate/runs/n-p2"))
    cfg = config_of(build_parser().parse_args(argv))
    resolved = asdict(cfg)
    assert detector_seconds(resolved.pop("time_minutes"), crop_phase_due(cfg)) == pytest.approx(100.0 * 60, abs=1e-9)
    phase = resolved.pop("crop_phase")
    assert {k: resolved[k] for k in VALIDATED_TRAIN_CONFIG} == VALIDATED_TRAIN_CONFIG
    assert set(resolved) - set(VALIDATED_TRAIN_CONFIG) == {"dataset", "out"}
    stage, split, position = stage_config(cfg)
    assert {"config": asdict(stage), "crop": cfg.heading_crop, "classes": cfg.crop_classes, "split": split,
            "position": position} == VALIDATED_CROP_STAGE and phase["steps"] == 7000
    # none of the recipe's values is on the command line: train takes them from detector/recipe.py
    assert not [a for a in argv if a.startswith("--") and a.lstrip("-").replace("-", "_") in RECIPE_FLAGS]


RECIPE_FLAGS = {"imgsz", "crop", "crop_focus", "repeat_thresh", "batch", "optimizer", "lr0", "kpt_sigma_end",
                "kpt_mode", "kpt_l1", "kpt_labelled", "kpt_turn_start", "kpt_heading", "heading_crop", "crop_classes",
                "model", "p2", "no_p2", "steps", "offset_gain", "position"}


def test_training_is_time_boxed_by_default_and_can_be_left_unboxed():
    ap = validate.build_parser()
    assert validate.time_box(ap.parse_args([])) == ["--time", "125.0"]
    assert validate.time_box(ap.parse_args(["--minutes", "30"])) == ["--time", "30.0"]
    assert validate.time_box(ap.parse_args(["--minutes", "0"])) == []


@pytest.mark.parametrize("argv, message", [(["--set", "data.focus=1.5"], "data.focus: 1.5 is outside [0, 1]"),
                                           (["--set", "loss.nope=1"], "loss.nope: no such recipe key"),
                                           (["--set", "data.window=48"], "crop (data.window): 48 is not a positive multiple of 32")])
def test_a_recipe_train_would_refuse_is_refused_before_any_data_stage(argv, message, capsys):
    ap = validate.build_parser()
    with pytest.raises(SystemExit):
        validate.check_recipe(ap, ap.parse_args(argv))
    assert message in capsys.readouterr().err
    validate.check_recipe(ap, ap.parse_args(["--set", "data.window=0", "loss.kpt_l1=1"]))  # whole images: fine
    args = ap.parse_args(["--set", "data.window=0", "--scales", "n", "s"])
    args.amp = "auto"
    argv = validate.train_command(args, Path("uov"), Path("out"), ["model.scale=s"])
    assert argv[:5] == ["train", "uov", "data.window=0", "model.scale=s", "--out"]  # keys right after the dataset
    assert "--set data.window=0" in validate.command_line(vars(args))


def test_predictions_made_another_way_are_made_again_with_their_evaluation(tmp_path):
    # an older validate's single-label predictions (no marker) must not stand under a new protocol
    out, calls = tmp_path / "runs" / "n-p2", []
    out.mkdir(parents=True)
    (out / "test-predictions.json").write_text("[]")
    (out / "eval.json").write_text("{}")
    run = Runner(tmp_path)
    run.record(f"predict_dataset({out / 'last.pt'}, uov, split='test')", 90.0)

    def predict(multi_label):
        calls.append(multi_label)
        return [{"image_id": 1, "score": 0.5}]

    preds = validate.predict_stage(run, out, Path("uov"), True, predict)
    assert calls == [True] and json.loads(preds.read_text()) == [{"image_id": 1, "score": 0.5}]
    assert not (out / "eval.json").exists()  # evaluated again by the caller
    assert [c["command"] for c in run.log] == [f"predict_dataset({out / 'last.pt'}, uov, split='test', multi_label=True, "
                                               "conf=0.001, max_det=1000, max_refine=300, vertical='lines')"]
    validate.predict_stage(run, out, Path("uov"), True, predict)  # made this way: kept
    assert calls == [True]
    validate.predict_stage(run, out, Path("uov"), False, predict)  # the other way: made again
    assert calls == [True, False] and len(run.log) == 1
    validate.predict_stage(run, out, Path("uov"), False, predict, vertical="off")  # corners not snapped: again
    assert calls == [True, False, False]


def test_predictions_deleted_to_redo_them_take_their_evaluation_with_them(tmp_path):
    out = tmp_path / "n-p2"
    out.mkdir()
    (out / "eval.json").write_text("{}")  # evaluated before test-predictions.json was deleted
    validate.predict_stage(Runner(tmp_path), out, Path("uov"), True, lambda multi_label: [])
    assert (out / "test-predictions.json").exists() and not (out / "eval.json").exists()


def test_results_markdown_says_how_the_test_predictions_were_made():
    made = {"runs": [{"predicted": "predict_dataset(w/last.pt, uov, split='test', multi_label=True)"}]}
    assert "multi-label, as Ultralytics' validation scores" in validate.protocol_line(made)[0]
    made["runs"][0]["predicted"] = "predict_dataset(w/last.pt, uov, split='test', multi_label=False)"
    assert "single-label" in validate.protocol_line(made)[0]
    assert "vanishing point" not in validate.protocol_line(made)[0]  # made before --vertical: not snapped
    made["runs"][0]["predicted"] = "predict_dataset(w/crop.pt, uov, split='test', multi_label=True, vertical='lines')"
    assert validate.protocol_line(made)[0].endswith("line segments (predict.vertical=lines)")
    assert validate.protocol_line({"runs": [{}]}) == []  # a results.json from before the marker


def test_the_results_say_how_many_frames_reached_the_detection_cap():
    preds = [{"image_id": 1, "frame_id": "a"}] * 3 + [{"image_id": 2, "frame_id": "b"}] * 2
    counts = validate.detection_cap_counts(preds, 4, 3)
    assert counts == {"detection_cap": 3, "test_frames_predicted": 4, "frames_at_detection_cap": 1}
    made = {"runs": [{"predicted": "predict_dataset(w/last.pt, uov, split='test', multi_label=True)", **counts}]}
    assert validate.protocol_line(made)[0].endswith("; 1 of 4 frames reached the cap of 3 detections")


def test_trains_into_reads_the_out_folder_not_a_mention():
    out = Path("runs/n-p2")
    assert trains_into("omnigen train uov --out runs/n-p2 --epochs 3", out)
    assert not trains_into("omnigen train uov --out runs/other --weights runs/n-p2/last.pt", out)
    assert not trains_into("omnigen eval runs/n-p2/last.pt uov --out runs/n-p2/eval.json", out)


def test_predictions_name_the_checkpoint_they_were_made_with(tmp_path):
    out, calls = tmp_path / "runs" / "n-p2", []
    out.mkdir(parents=True)
    run = Runner(tmp_path)

    def predict(multi_label):
        calls.append(multi_label)
        return []

    validate.predict_stage(run, out, Path("uov"), True, predict)
    assert f"predict_dataset({out / 'last.pt'}, " in (out / "predicted").read_text()
    validate.predict_stage(run, out, Path("uov"), True, predict, weights=out / "crop.pt")  # another checkpoint
    assert calls == [True, True] and f"predict_dataset({out / 'crop.pt'}, " in (out / "predicted").read_text()
    assert [c["command"].split(",")[0] for c in run.log] == [f"predict_dataset({out / 'crop.pt'}"]


def test_the_results_say_when_the_crop_stage_was_trained_apart():
    made = {"runs": [{"predicted": "predict_dataset(w/crop.pt, uov, split='test', multi_label=True)"}]}
    assert len(validate.protocol_line(made)) == 1  # predicted with the detector's own stage
    made["runs"][0]["crop_stage"] = {"steps_done": 4000, "seconds": 812.5, "score_split": "test",
                                     "score": {"corner_rel": 0.17, "front": 0.85, "class_acc": 0.84}}
    line = validate.protocol_line(made)[1]
    assert "omnigen train-crop" in line and "4000 steps, 812.5 s)" in line
    assert "corner error rel 0.170, front right 0.850, class accuracy 0.840" in line
    made["runs"][0]["crop_stage"]["position"] = True
    assert "812.5 s, told where each crop was cut (crop_stage.position))" in validate.protocol_line(made)[1]
    made["runs"][0]["crop_stage"]["config"] = {"offset_gain": 0.3}
    assert "(crop_stage.position), an L1 term on the faces' offset (crop_stage.offset_gain=0.3))" in validate.protocol_line(made)[1]
    made["runs"][0]["crop_stage"]["by"] = "omnigen train"  # the run's own second phase
    assert "trained again apart from the detector (the run's second phase, 4000 steps" in validate.protocol_line(made)[1]


def test_predictions_of_a_checkpoint_rewritten_in_place_are_made_again(tmp_path):
    # train-crop writes each new stage into the same crop.pt: its path alone cannot say what predicted
    out, calls = tmp_path / "runs" / "n-p2", []
    out.mkdir(parents=True)
    weights = out / "crop.pt"
    weights.write_bytes(b"a stage of 8000 steps")
    run = Runner(tmp_path)

    def predict(multi_label):
        calls.append(multi_label)
        return []

    validate.predict_stage(run, out, Path("uov"), True, predict, weights=weights)
    validate.predict_stage(run, out, Path("uov"), True, predict, weights=weights)
    assert calls == [True]
    weights.write_bytes(b"a stage of 4000 steps")
    validate.predict_stage(run, out, Path("uov"), True, predict, weights=weights)
    assert calls == [True, True] and validate.file_digest(weights) in (out / "predicted").read_text()


def test_the_test_split_is_predicted_as_the_recipe_says_with_no_option_of_validate_s_own(tmp_path, monkeypatch):
    """predict.vertical is a recipe key like the others: validate has no flag for it (the command
    RESULTS.md prints names none), and `--set predict.vertical=off` reaches the prediction."""
    import omnigen.detector.prediction.predict as predict

    seen: list[dict] = []
    monkeypatch.setattr(predict, "predict_dataset", lambda weights, uov, **kw: seen.append(kw) or [])
    ap = validate.build_parser()
    assert "--vertical" not in validate.command_line(vars(ap.parse_args([])))
    with pytest.raises(SystemExit):
        ap.parse_args(["--vertical", "off"])
    recipe = validate.run_recipe(ap.parse_args(["--set", "predict.vertical=off", "optim.batch=3"]))
    out = tmp_path / "n-p2"
    out.mkdir()
    validate.predict_test_split(Runner(tmp_path), out, Path("uov"), recipe, "cpu")
    assert [(kw["vertical"], kw["batch"], kw["imgsz"]) for kw in seen] == [("off", 3, recipe.model.imgsz)]
    assert "vertical='off'" in (out / "predicted").read_text()


def test_the_command_line_names_only_what_differs_from_the_defaults():
    assert command_line({"kitti": "k", "epochs": 3, "jobs": 1, "scales": ["n", "s"], "fresh": False}) == \
        "python benchmarks/validate.py --kitti k --epochs 3 --jobs 1 --scales n s"
    # a switch on by default is said only when turned off
    assert command_line({"cache": True}) == "python benchmarks/validate.py"
    assert command_line({"cache": False}) == "python benchmarks/validate.py --no-cache"
    assert "cache" not in command_line(vars(validate.build_parser().parse_args([])))
