"""The crop stage trained apart (detector/training/crop_train.py, omnigen train-crop)."""

from __future__ import annotations

import os

from dataclasses import asdict

import numpy as np
import pytest
import torch

from omnigen.cli import main as omnigen
from omnigen.conventions import FLIP_IDX
from omnigen.detector.model.boxes import box_area
from omnigen.detector.model.checkpoint import load_checkpoint, load_model
from omnigen.detector.model.crop_stage import MIRROR_HEADING, jitter_boxes, mirror_corners
from omnigen.detector.training.crop_train_config import CropTrainConfig
from omnigen.detector.training.crop_train import (CropSet, attach_stage, cut_crops, draw_weights, mirror_batch,
                                         new_stage, score_stage, train_stage)
from omnigen.detector.data.samples import KeypointDataset, split_frames
from omnigen.detector.model.heading import image_heading
from omnigen.taxonomy import load_taxonomy


def test_jitter_boxes_draws_from_the_generator_given_and_else_torchs_as_before():
    boxes = torch.tensor([[10.0, 20.0, 50.0, 40.0], [0.0, 0.0, 8.0, 16.0]])
    a = jitter_boxes(boxes, torch.Generator().manual_seed(3))
    b = jitter_boxes(boxes, torch.Generator().manual_seed(3))
    assert torch.equal(a, b) and not torch.equal(a, boxes)
    torch.manual_seed(5)
    wh = boxes[:, 2:] - boxes[:, :2]
    n1, n2 = torch.randn_like(wh), torch.randn_like(wh)  # what the joint training drew before the argument
    centre = (boxes[:, :2] + boxes[:, 2:]) / 2 + n1 * 0.06 * wh
    wh = wh * torch.exp(n2 * 0.1)
    torch.manual_seed(5)
    assert torch.allclose(jitter_boxes(boxes), torch.cat([centre - wh / 2, centre + wh / 2], 1))


def test_mirroring_a_batch_mirrors_the_heading_as_image_heading_of_the_mirrored_corners():
    g = torch.Generator().manual_seed(0)
    xy = torch.rand(6, 8, 2, generator=g) * 2 - 1
    mask = torch.rand(6, 8, generator=g) > 0.2
    area = torch.full((6,), 4.0)
    heading = image_heading(xy, area, mask)
    x = torch.rand(6, 3, 16, 16, generator=g)
    flip = torch.tensor([True, False, True, True, False, True])
    mx, mc, mm, mh, none = mirror_batch(x, xy, mask, heading, flip)
    assert none is None  # no positions given, none returned
    mirrored_xy = xy[:, list(FLIP_IDX)] * torch.tensor([-1.0, 1.0])
    assert torch.allclose(mh[flip], image_heading(mirrored_xy, area, mask[:, list(FLIP_IDX)])[flip], atol=1e-6)
    assert torch.equal(mh[~flip], heading[~flip]) and torch.equal(mc[flip], mirrored_xy[flip])
    assert torch.equal(mx[flip], x[flip].flip(-1)) and torch.equal(mm[flip], mask[flip][:, list(FLIP_IDX)])
    assert torch.equal(x, x.clone())  # the inputs are not written
    assert MIRROR_HEADING == (-1.0, 1.0, 1.0)


def test_draw_weights_balance_zero_is_uniform_and_one_gives_every_class_an_equal_share():
    cls = torch.tensor([0] * 90 + [1] * 9 + [2])
    uniform = draw_weights(cls, 0.0)
    assert np.allclose(uniform, 1 / 100)
    equal = draw_weights(cls, 1.0)
    shares = [equal[cls.numpy() == c].sum() for c in range(3)]
    assert np.allclose(shares, 1 / 3)
    half = draw_weights(cls, 0.5)
    assert half[cls.numpy() == 2].sum() > uniform[cls.numpy() == 2].sum() and np.isclose(half.sum(), 1.0)


def test_config_refuses_bad_values_naming_the_field():
    for kw, field in (({"steps": 0}, "steps"), ({"batch": -1}, "batch"), ({"copies": 0}, "copies"),
                      ({"balance": 1.5}, "balance"), ({"lr": 0.0}, "lr"), ({"amp": "fp16"}, "amp")):
        with pytest.raises(ValueError, match=field):
            CropTrainConfig(**kw)


def _crops(ds, split: str, copies: int, jitter: bool, seed: int = 0) -> CropSet:
    data = KeypointDataset(ds.root, load_taxonomy("fine"), 128, split_frames(ds.root, split))
    return cut_crops(data, 32, copies, jitter, torch.Generator().manual_seed(seed))


def test_cut_crops_gives_copies_of_each_object_with_targets_in_crop_units(split_fake_dataset):
    one = _crops(split_fake_dataset, "train", 1, jitter=False)
    three = _crops(split_fake_dataset, "train", 3, jitter=True)
    assert len(three) == 3 * len(one) > 0
    assert one.crops.dtype == torch.uint8 and one.crops.shape[1:] == (3, 32, 32)
    assert torch.equal(three.cls, one.cls.repeat_interleave(3))
    # about the true boxes the labelled corners lie near the crop (a box spans +-1/(1 + 2 margin))
    assert one.corners[one.mask].abs().max() < 3
    assert torch.allclose(one.true_area, box_area(one.boxes))
    # moved boxes differ and are drawn from the generator: the same seed cuts the same crops
    assert not torch.equal(three.boxes[::3], one.boxes)
    again = _crops(split_fake_dataset, "train", 3, jitter=True)
    assert torch.equal(again.crops, three.crops) and torch.equal(again.boxes, three.boxes)


def test_training_learns_and_a_stopped_run_resumes_to_the_same_weights(split_fake_dataset, tmp_path):
    data = _crops(split_fake_dataset, "train", 2, jitter=True)
    cfg = CropTrainConfig(steps=40, batch=16, seed=1)
    net = new_stage(32, 12, cfg.seed)
    history = train_stage(data, net, cfg)
    first, last = np.mean([h["crop_corners"] for h in history[:5]]), np.mean([h["crop_corners"] for h in history[-5:]])
    assert last < first
    assert set(history[0]) == {"crop_corners", "heading_crop", "crop_offset", "crop_cls"}

    partial = tmp_path / "stage.pt.partial"

    class Stop(Exception):
        pass

    def stop_at_17(step, parts):
        if step == 17:
            raise Stop

    stopped = new_stage(32, 12, cfg.seed)
    with pytest.raises(Stop):
        train_stage(data, stopped, cfg, partial=partial, save_interval=0.0, on_step=stop_at_17)
    assert partial.exists()
    resumed = new_stage(32, 12, cfg.seed)
    rest = train_stage(data, resumed, cfg, partial=partial, save_interval=0.0)
    assert len(rest) == cfg.steps
    for (k, a), b in zip(net.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(a, b), k
    # the finished state stays until the caller has written its result: a rerun returns it at once
    assert partial.exists()
    again = new_stage(32, 12, cfg.seed)
    assert train_stage(data, again, cfg, partial=partial, on_step=stop_at_17) == rest
    assert all(torch.equal(a, b) for a, b in zip(again.state_dict().values(), resumed.state_dict().values()))
    # a partial run of other arguments, or of other crops or identity, is refused, naming the file
    with pytest.raises(ValueError, match="stage.pt.partial"):
        train_stage(data, new_stage(32, 12, 1), CropTrainConfig(steps=40, batch=8, seed=1), partial=partial)
    with pytest.raises(ValueError, match="stage.pt.partial"):
        train_stage(data, new_stage(32, 12, 1), cfg, partial=partial, identity={"crop": 48})


def test_new_stage_leaves_torchs_global_generator_alone():
    torch.manual_seed(9)
    expected = torch.rand(3)
    torch.manual_seed(9)
    a = new_stage(32, 0, 4)
    assert torch.equal(torch.rand(3), expected)
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), new_stage(32, 0, 4).state_dict().values()))


def test_score_stage_scores_a_stage_that_knows_the_answers_as_exact_and_a_turned_one_by_layout(split_fake_dataset):
    data = _crops(split_fake_dataset, "test", 1, jitter=True)
    data.heading[data.heading.norm(dim=-1) < 1e-3] = torch.tensor([1.0, 0.0, 0.0])  # every object has a front

    class Oracle(torch.nn.Module):
        """Gives the true outputs for the crops, and for their mirror images the mirrored ones."""

        def __init__(self, corners, heading, turn=False):
            super().__init__()
            self.num_classes, self.calls = 12, 0
            logits = torch.nn.functional.one_hot(data.cls, 12).float() * 10
            self.y = torch.cat([heading * (-1 if turn else 1), corners.flatten(1), logits], 1)
            self.ym = torch.cat([heading * torch.tensor(MIRROR_HEADING) * (-1 if turn else 1),
                                 mirror_corners(corners).flatten(1), logits], 1)

        def forward(self, x, where=None):  # a crop net's interface; this one reads no positions
            self.calls += 1
            return self.y if self.calls % 2 else self.ym

    s = score_stage(Oracle(data.corners, data.heading), data, batch=len(data))
    assert s.objects == len(data) and s.corner_rel < 1e-5 and s.layout_rel < 1e-5 and s.placed_rel < 1e-5
    assert s.vertical_rel < 1e-5  # the bottom face's offset from the top face: exact too
    assert s.front == 1.0 and s.placed_front == 1.0 and s.class_acc == 1.0
    # the heading turned: the corners are faced the other way, wrong by the turn and right as a layout
    t = score_stage(Oracle(data.corners, data.heading, turn=True), data, batch=len(data))
    assert t.front == 0.0 and t.corner_rel > 0.1 and t.layout_rel < 1e-5
    assert t.placed_rel < 1e-5 and t.placed_front == 1.0  # as placed, before the heading turned them
    assert t.vertical_rel < 1e-5  # a turn keeps each face, so the offset between them
    net = score_stage(new_stage(32, 12, 0), data)  # an untrained net: a number, not a crash
    assert 0 < net.layout_rel and 0 <= net.front <= 1 and 0 <= net.class_acc <= 1 and net.vertical_rel > 0
    lifted = data.corners.clone()
    lifted[:, 4:, 1] -= 0.1  # the bottom face moved up by 0.1 crop units: the offset is off by that
    v = score_stage(Oracle(lifted, data.heading), data, batch=len(data)).vertical_rel
    full = data.mask.all(1)
    half = (data.boxes[:, 2:] - data.boxes[:, :2]).amax(1) * 0.6  # crop_stage.half_side
    assert v == pytest.approx(float((0.1 * half / data.true_area.sqrt())[full].median()), rel=1e-4)


def test_attach_stage_replaces_only_the_crop_stage_and_adds_one_where_there_is_none(detector_checkpoint, tmp_path):
    for heading_crop in (32, 0):
        path = detector_checkpoint(tmp_path / f"det{heading_crop}.pt", heading_crop, crop_classes=bool(heading_crop))
        state = load_checkpoint(path)
        net = new_stage(32, 12, 7)
        out = attach_stage(state, net, 32, {"trained": "apart"})
        assert out["config"]["heading_crop"] == 32 and out["config"]["crop_classes"] is True
        assert out["crop_stage"] == {"trained": "apart"}
        for k, v in state["model"].items():
            if not k.startswith("crop_net."):
                assert out["model"][k] is v
        for k, v in net.state_dict().items():
            assert torch.equal(out["model"][f"crop_net.{k}"], v)
        assert state["config"]["heading_crop"] == heading_crop  # the input state is not changed
        save = tmp_path / f"with{heading_crop}.pt"
        from omnigen.detector.model.checkpoint import save_checkpoint

        save_checkpoint(save, out)
        model, _ = load_model(save)
        assert model.crop_net is not None and model.crop_net.num_classes == 12


def test_train_crop_command_writes_a_checkpoint_predict_reads_and_guards_its_files(
        split_fake_dataset, detector_checkpoint, tmp_path, capsys):
    weights = detector_checkpoint(tmp_path / "det.pt", 32, crop_classes=True)
    before = weights.read_bytes()
    out = tmp_path / "crop.pt"
    args = ["train-crop", str(split_fake_dataset.root), "--weights", str(weights), "--out", str(out),
            "--steps", "6", "--batch", "8", "--copies", "1"]
    assert omnigen(args) == 0
    text = capsys.readouterr().out
    assert "trained with the detector" in text and "trained apart" in text and "wrote" in text
    assert weights.read_bytes() == before  # the input is never written
    assert not out.with_name("crop.pt.partial").exists()  # removed once crop.pt is written
    state = load_checkpoint(out)
    rec = state["crop_stage"]
    assert rec["trained"] == "apart" and rec["steps_done"] == 6 and rec["crop"] == 32 and rec["classes"] is True
    assert rec["split"] is True and state["config"]["crop_split"] is True  # the classes from a net of their own
    assert rec["config"] == asdict(CropTrainConfig(steps=6, batch=8, copies=1))
    det = load_checkpoint(weights)
    assert all(torch.equal(state["model"][k], v) for k, v in det["model"].items() if not k.startswith("crop_net."))
    assert {k for k in state["model"] if k.startswith("crop_net.")} != {k for k in det["model"] if k.startswith("crop_net.")}
    # the same arguments again: nothing to do; other arguments: refused, naming the file
    mtime = out.stat().st_mtime_ns
    assert omnigen(args) == 0 and "already trained" in capsys.readouterr().out and out.stat().st_mtime_ns == mtime
    assert omnigen(args[:-2] + ["--copies", "2"]) == 1
    assert str(out) in capsys.readouterr().err
    # the input checkpoint as the output, and a name that is no checkpoint's: refused
    assert omnigen(args[:4] + ["--out", str(weights)] + args[6:]) == 1
    assert "refusing to write onto an input" in capsys.readouterr().err
    os.link(weights, tmp_path / "same-weights.pt")  # the weights under another name: the same file
    assert omnigen(args[:4] + ["--out", str(tmp_path / "same-weights.pt")] + args[6:]) == 1
    assert "refusing to write onto an input" in capsys.readouterr().err
    assert omnigen(args[:4] + ["--out", str(tmp_path / "crop.txt")] + args[6:]) == 1
    assert ".pt" in capsys.readouterr().err
    # predict reads the written checkpoint as it reads the detector's
    pred_dir = tmp_path / "pred"
    assert omnigen(["predict", str(out), str(split_fake_dataset.root / "images"), "--out", str(pred_dir),
                    "--no-overlays"]) == 0
    assert (pred_dir / "predictions.json").exists()


def test_a_split_stage_trains_both_nets_and_is_attached_and_loaded_as_one(split_fake_dataset, detector_checkpoint,
                                                                         tmp_path):
    from omnigen.detector.model.checkpoint import save_checkpoint
    from omnigen.detector.model.crop_stage import SplitCropNet

    data = _crops(split_fake_dataset, "train", 1, jitter=True)
    net = new_stage(32, 12, 0, split=True)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    train_stage(data, net, CropTrainConfig(steps=3, batch=8))
    for part in ("corners", "classes"):
        assert any(not torch.equal(v, before[k]) for k, v in net.state_dict().items() if k.startswith(part + ".")), part
    state = attach_stage(load_checkpoint(detector_checkpoint(tmp_path / "det.pt", 32, crop_classes=True)), net, 32, {})
    assert state["config"]["crop_split"] is True
    assert not any(k.startswith("crop_net.out.") for k in state["model"])  # the one net's tensors are gone
    save_checkpoint(tmp_path / "split.pt", state)
    model, _ = load_model(tmp_path / "split.pt")
    assert isinstance(model.crop_net, SplitCropNet)
    assert all(torch.equal(model.state_dict()[f"crop_net.{k}"], v) for k, v in net.state_dict().items())


def test_train_crop_help_does_not_import_torch():
    import subprocess
    import sys

    code = ("import sys; from omnigen.cli import build_parser; build_parser(); "
            "sys.exit(1 if 'torch' in sys.modules else 0)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_joint_training_builds_one_crop_net_and_the_crop_phase_gives_the_classes_their_own():
    """Trained with the detector the stage is one CropNet, not told where its crops were cut; the
    split net and the position come with the second phase (attach_stage)."""
    from omnigen.detector.model.crop_stage import CropNet
    from omnigen.detector.model.network import KeypointDetector
    from omnigen.detector.training.train import TrainConfig

    cfg = TrainConfig(dataset="d", out="o", heading_crop=32, crop_classes=True, width=0.0625, depth=0.33
                      ).model_config(12)
    assert (cfg.crop_classes, cfg.crop_split, cfg.crop_position) == (True, False, False)
    assert type(KeypointDetector(cfg).crop_net) is CropNet


def test_train_crop_trains_a_stage_without_classes_as_one_net(split_fake_dataset, detector_checkpoint, tmp_path):
    from omnigen.detector.model.crop_stage import CropNet

    weights = detector_checkpoint(tmp_path / "det.pt", 32)
    out = tmp_path / "plain.pt"
    assert omnigen(["train-crop", str(split_fake_dataset.root), "--weights", str(weights), "--out", str(out),
                    "--steps", "2", "--batch", "4", "--copies", "1", "--no-classes"]) == 0
    state = load_checkpoint(out)
    assert state["crop_stage"]["classes"] is False and state["crop_stage"]["split"] is False
    assert state["config"]["crop_classes"] is False and state["config"]["crop_split"] is False
    model, _ = load_model(out)
    assert type(model.crop_net) is CropNet and model.crop_net.num_classes == 0


def test_train_crop_trains_again_for_a_detector_rewritten_in_place_and_refuses_bad_crop_sides(
        split_fake_dataset, detector_checkpoint, tmp_path, capsys):
    weights = detector_checkpoint(tmp_path / "det.pt", 32, crop_classes=True)
    out = tmp_path / "crop.pt"
    args = ["train-crop", str(split_fake_dataset.root), "--weights", str(weights), "--out", str(out),
            "--steps", "2", "--batch", "4", "--copies", "1"]
    assert omnigen(args) == 0
    capsys.readouterr()
    state = load_checkpoint(weights)
    state["model"] = {k: v + 1 if v.is_floating_point() else v for k, v in state["model"].items()}
    from omnigen.detector.model.checkpoint import save_checkpoint

    save_checkpoint(weights, state)  # the detector trained again into the same file
    assert omnigen(args) == 1 and "not trained with these arguments" in capsys.readouterr().err
    for bad in ("-16", "0"):  # outside the range: refused as the arguments are parsed
        with pytest.raises(SystemExit) as exc:
            omnigen([*args[:4], "--out", str(tmp_path / f"c{bad}.pt"), *args[6:], "--crop", bad])
        assert exc.value.code == 2 and "is outside [16, 1024]" in capsys.readouterr().err
    assert omnigen([*args[:4], "--out", str(tmp_path / "c40.pt"), *args[6:], "--crop", "40"]) == 1
    assert "positive multiple of 16" in capsys.readouterr().err


def test_bf16_training_runs_and_learns(split_fake_dataset):
    data = _crops(split_fake_dataset, "train", 2, jitter=True)
    net = new_stage(32, 12, 1, split=True)
    history = train_stage(data, net, CropTrainConfig(steps=40, batch=16, seed=1, amp="bf16"))
    assert np.mean([h["crop_corners"] for h in history[-5:]]) < np.mean([h["crop_corners"] for h in history[:5]])
    assert all(p.dtype == torch.float32 for p in net.parameters())  # autocast: the weights stay float32


def test_train_crop_tells_the_stage_where_its_crops_were_and_keeps_stages_written_before_the_choice(
        split_fake_dataset, detector_checkpoint, tmp_path, capsys):
    """--position: every crop carries where it was cut (mirrored with it), the stage is trained and
    written with crop_position, load_model builds it again and predict runs it; a stage written
    before --position existed counts as one without, so its rerun is still 'already trained'."""
    from omnigen.detector.model.checkpoint import save_checkpoint
    from omnigen.detector.model.crop_stage import crop_position, mirror_position

    data = _crops(split_fake_dataset, "train", 1, jitter=True)
    letterboxed = torch.tensor([128, 128])  # _crops' input size
    assert data.where is not None and torch.allclose(data.where, crop_position(data.boxes, letterboxed))
    flip = torch.arange(len(data)) % 2 == 0
    *_, where = mirror_batch(data.crops.float(), data.corners, data.mask, data.heading, flip, data.where)
    assert torch.equal(where[flip], mirror_position(data.where[flip])) and torch.equal(where[~flip], data.where[~flip])
    weights = detector_checkpoint(tmp_path / "det.pt", 32, crop_classes=True)
    out = tmp_path / "where.pt"
    args = ["train-crop", str(split_fake_dataset.root), "--weights", str(weights), "--out", str(out),
            "--steps", "2", "--batch", "4", "--copies", "1", "--position"]
    assert omnigen(args) == 0
    state = load_checkpoint(out)
    assert state["crop_stage"]["position"] is True and state["config"]["crop_position"] is True
    model, _ = load_model(out)
    assert model.crop_net.position and model.crop_net.corners.position
    assert all(torch.equal(model.state_dict()[k], v) for k, v in state["model"].items())
    pred_dir = tmp_path / "pred"
    assert omnigen(["predict", str(out), str(split_fake_dataset.root / "images"), "--out", str(pred_dir),
                    "--no-overlays"]) == 0
    capsys.readouterr()
    assert omnigen(args[:-1]) == 0 and "already trained" in capsys.readouterr().out  # --position is the default
    assert omnigen([*args[:-1], "--no-position"]) == 1 and "not trained with these arguments" in capsys.readouterr().err
    plain = tmp_path / "plain.pt"
    assert omnigen([*args[:4], "--out", str(plain), *args[6:-1], "--no-position"]) == 0
    old = load_checkpoint(plain)
    del old["crop_stage"]["position"]  # as train-crop wrote it before --position (schema 1)
    del old["config"]["crop_position"]
    del old["schema"]
    save_checkpoint(plain, old)
    capsys.readouterr()
    assert omnigen([*args[:4], "--out", str(plain), *args[6:-1], "--no-position"]) == 0
    assert "already trained" in capsys.readouterr().out


def test_the_offset_term_is_the_l1_of_the_faces_offset_and_counts_only_fully_labelled_objects():
    from omnigen.detector.training.crop_train import offset_loss

    corners = torch.zeros(3, 8, 2)
    corners[:, 4:, 1] = 0.5  # bottom face 0.5 crop units under the top one
    mask = torch.ones(3, 8, dtype=torch.bool)
    assert float(offset_loss(corners, corners, mask)) == 0.0
    placed = corners.clone()
    placed[0, 4:] += torch.tensor([0.1, -0.2])  # object 0's bottom face moved: offset off by (0.1, -0.2)
    placed[1] += 0.3  # object 1 moved whole: its offset is right
    assert float(offset_loss(placed, corners, mask)) == pytest.approx(0.3 / 3)
    mask[0, 5] = False  # object 0 not fully labelled: it does not count
    assert float(offset_loss(placed, corners, mask)) == pytest.approx(0.0)
    assert float(offset_loss(placed, corners, torch.zeros(3, 8, dtype=torch.bool))) == 0.0


def test_train_crop_records_the_offset_gain_and_keeps_stages_written_before_it(
        split_fake_dataset, detector_checkpoint, tmp_path, capsys):
    """--offset-gain (0.3 by default) adds the term to the stage's loss and its record; a stage
    written before the term existed counts as one of gain 0, so its rerun is 'already trained'."""
    from omnigen.detector.model.checkpoint import save_checkpoint

    weights = detector_checkpoint(tmp_path / "det.pt", 32, crop_classes=True)
    out = tmp_path / "offset.pt"
    args = ["train-crop", str(split_fake_dataset.root), "--weights", str(weights), "--out", str(out),
            "--steps", "2", "--batch", "4", "--copies", "1"]
    assert omnigen(args) == 0
    rec = load_checkpoint(out)["crop_stage"]
    assert rec["config"]["offset_gain"] == 0.3 and "crop_offset" in rec["last_losses"]
    capsys.readouterr()
    assert omnigen([*args, "--offset-gain", "1"]) == 1 and "not trained with these arguments" in capsys.readouterr().err
    plain = tmp_path / "plain.pt"
    assert omnigen([*args[:4], "--out", str(plain), *args[6:], "--offset-gain", "0"]) == 0
    assert "crop_offset" not in load_checkpoint(plain)["crop_stage"]["last_losses"]
    old = load_checkpoint(plain)
    del old["crop_stage"]["config"]["offset_gain"]  # as train-crop wrote it before --offset-gain (schema 1)
    del old["schema"]
    save_checkpoint(plain, old)
    capsys.readouterr()
    assert omnigen([*args[:4], "--out", str(plain), *args[6:], "--offset-gain", "0"]) == 0
    assert "already trained" in capsys.readouterr().out
    with pytest.raises(ValueError, match="offset_gain"):
        CropTrainConfig(offset_gain=-1.0)
