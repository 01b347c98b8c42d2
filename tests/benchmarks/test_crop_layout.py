"""benchmarks/crop_layout.py: its box noise is what it says, and its score is `omnigen eval`'s
corner error (its crop units and mirror are the detector's crop stage's, tested there)."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import crop_layout as cl  # noqa: E402
from omnigen.detector.crop_stage import CENTRE_JITTER, SIDE_JITTER  # noqa: E402
from omnigen.conventions import TURN_IDX  # noqa: E402


def _crops(keypoints: np.ndarray, boxes: np.ndarray) -> cl.LayoutCrops:
    n = len(boxes)
    return cl.LayoutCrops(images=np.zeros((n, 16, 16, 3), np.uint8), boxes=boxes, true_boxes=boxes,
                          keypoints=keypoints, labelled=np.ones((n, 8), bool), views=np.zeros(n, np.int64),
                          classes=np.array(["car"] * n, dtype=object), frames=np.zeros(n, np.int64))


def test_moved_boxes_carry_the_stated_noise_and_none_at_zero():
    boxes = np.tile([[100.0, 50.0, 140.0, 70.0]], (20000, 1))
    moved = cl.move_boxes(boxes, np.random.default_rng(0), 1.0)
    wh = boxes[:, 2:] - boxes[:, :2]
    shift = ((moved[:, :2] + moved[:, 2:]) - (boxes[:, :2] + boxes[:, 2:])) / 2 / wh
    assert np.allclose(shift.std(0), CENTRE_JITTER, atol=0.003)
    assert np.allclose(np.log((moved[:, 2:] - moved[:, :2]) / wh).std(0), SIDE_JITTER, atol=0.003)
    assert np.array_equal(cl.move_boxes(boxes, np.random.default_rng(0), 0.0), boxes)


def test_score_is_zero_on_the_truth_and_forgives_only_the_turn_in_layout():
    rng = np.random.default_rng(1)
    boxes = np.array([[0.0, 0.0, 40.0, 20.0]] * 3)
    kp = rng.random((3, 8, 2)) * np.array([40.0, 20.0])
    crops = _crops(kp, boxes)
    perfect = cl.score(kp, crops)
    assert perfect.rel == 0 and perfect.oks50 == 1 and perfect.oks75 == 1 and perfect.objects == 3
    turned = cl.score(kp[:, list(TURN_IDX)], crops)
    assert turned.rel > 0.1 and turned.layout_rel == 0
    # a corner 0.3 sqrt(area) off everywhere: OKS exp(-0.09 / (2 * 0.0625)) = 0.49, under 0.5
    off = cl.score(kp + np.array([0.3 * np.sqrt(800.0), 0.0]), crops)
    assert np.isclose(off.rel, 0.3) and off.oks50 == 0


def test_soft_argmax_reads_a_peaked_map_at_its_cell_and_a_flat_one_at_the_middle():
    s = 16
    centres = (torch.arange(s, dtype=torch.float32) + 0.5) / s * 2 - 1
    maps = torch.zeros(2, 8, s, s)
    maps[0, :, 3, 12] = 100.0  # row 3 (y), column 12 (x)
    xy = cl.soft_argmax(maps, centres)
    assert xy.shape == (2, 8, 2)
    assert torch.allclose(xy[0], torch.tensor([centres[12], centres[3]]).expand(8, 2), atol=1e-4)
    assert torch.allclose(xy[1], torch.zeros(8, 2), atol=1e-6)


def test_integral_head_gives_corners_in_crop_units_and_learns_the_regressors_target():
    net = cl.build_model(width=4, crop=32, head="integral")
    out = net(torch.rand(3, 3, 32, 32))
    assert out.shape == (3, 16) and bool((out.abs() < 1).all())
    assert out.requires_grad  # trained by the same L1 as the regressor
    assert cl.build_model(width=4, crop=32)(torch.rand(3, 3, 32, 32)).shape == (3, 16)
    with pytest.raises(ValueError, match="regress, integral"):
        cl.build_model(head="mean")


def test_main_trains_and_scores_either_head_end_to_end(split_fake_dataset, capsys):
    for head in cl.HEADS:
        assert cl.main([str(split_fake_dataset.root), "--steps", "3", "--batch", "8", "--crop", "32", "--copies", "1",
                        "--head", head, "--threads", "1"]) == 0
        last = capsys.readouterr().out.strip().splitlines()[-1]
        assert last.startswith(f"crop_layout ({head}): rel ") and "template" in last


def test_a_detectors_stage_scored_on_its_crops_places_the_corners_prediction_places(detector_checkpoint, tmp_path):
    """stage_corners on crops cut ahead (as collect stores them, uint8) against crop_stage.refine
    on the whole image: the same mirror average, units and turn, up to the crops' rounding."""
    from omnigen.detector.crop_stage import crop_boxes, refine

    net = cl.load_stage(detector_checkpoint(tmp_path / "crop.pt", 16), 16)
    torch.manual_seed(3)
    image = (torch.rand(1, 3, 48, 64) * 255).round()
    boxes = torch.tensor([[5.0, 6.0, 30.0, 20.0], [30.0, 10.0, 60.0, 44.0], [10.0, 20.0, 22.0, 40.0]])
    index = torch.zeros(3, dtype=torch.long)
    crops = crop_boxes(image, index, boxes, 16).round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()
    layout = _crops(np.zeros((3, 8, 2)), boxes.numpy().astype(np.float64))
    layout.images = crops
    mine = cl.stage_corners(net, layout)
    with torch.no_grad():
        theirs, _ = refine(net, 16, image / 255, index, boxes, torch.zeros(3, 8, 3))
    assert mine.shape == (3, 8, 2)
    assert np.allclose(mine, theirs[..., :2].numpy(), atol=0.05)


def test_main_scores_a_detectors_stage_beside_its_own_net_and_refuses_a_mismatch(split_fake_dataset,
                                                                                  detector_checkpoint, tmp_path, capsys):
    weights = detector_checkpoint(tmp_path / "crop.pt", 16)
    args = [str(split_fake_dataset.root), "--steps", "2", "--batch", "8", "--copies", "1", "--threads", "1",
            "--weights", str(weights)]
    assert cl.main([*args, "--crop", "16"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-2].startswith(f"crop_layout: the detector's crop stage ({weights}): rel ")
    assert lines[-1].startswith("crop_layout (regress): rel ")
    with pytest.raises(SystemExit, match="pass --crop 16"):
        cl.main([*args, "--crop", "32"])
    with pytest.raises(SystemExit, match="no crop stage"):
        cl.main([*args[:-1], str(detector_checkpoint(tmp_path / "plain.pt", 0)), "--crop", "16"])
