"""benchmarks/crop_layout.py: its box noise is what it says, and its score is `omnigen eval`'s
corner error (its crop units and mirror are the detector's crop stage's, tested there)."""

import sys
from pathlib import Path

import numpy as np

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
