"""benchmarks/heading_visibility.py: its label cannot come from the cuboid, its crops and score are right."""

import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import heading_visibility as hv  # noqa: E402
from omnigen.conventions import TURN_IDX  # noqa: E402


def _side_view() -> np.ndarray:
    """A car seen from its left side, front to the image right: front corners at x 80, rear at x 20."""
    kp = np.zeros((8, 2))
    kp[[0, 1, 4, 5], 0] = [80, 84, 80, 84]
    kp[[2, 3, 6, 7], 0] = [24, 20, 24, 20]
    kp[:4, 1], kp[4:, 1] = 30, 60
    return kp


def test_the_label_flips_when_the_same_cuboid_is_turned_around():
    kp, bbox = _side_view(), np.array([20.0, 30.0, 84.0, 60.0])
    assert hv.facing_right(kp, bbox, 0.25) is True
    turned = kp[list(TURN_IDX)]  # the same eight points, front and rear swapped
    assert sorted(map(tuple, turned)) == sorted(map(tuple, kp))
    assert hv.facing_right(turned, bbox, 0.25) is False


def test_front_and_rear_views_carry_no_label():
    kp, bbox = _side_view(), np.array([20.0, 30.0, 84.0, 60.0])
    kp[[0, 1, 4, 5], 0] = [50, 54, 50, 54]
    kp[[2, 3, 6, 7], 0] = [52, 48, 52, 48]
    assert hv.facing_right(kp, bbox, 0.25) is None
    assert hv.facing_right(kp, bbox, 0.0) is True  # any offset counts when asked to


def test_square_crop_centres_the_box_and_pads_outside_the_image():
    image = np.zeros((100, 200, 3), np.uint8)
    image[40:60, 90:110] = 255  # a white square at the box
    crop = hv.square_crop(image, np.array([90.0, 40.0, 110.0, 60.0]), 24, margin=0.1)
    assert crop.shape == (24, 24, 3)
    assert crop[12, 12].tolist() == [255, 255, 255] and crop[0, 0].tolist() == [0, 0, 0]
    edge = hv.square_crop(image + 7, np.array([-10.0, -10.0, 10.0, 10.0]), 20, margin=0.0)
    assert edge[0, 0].tolist() == [0, 0, 0] and edge[15, 15].tolist() == [7, 7, 7]


def test_balanced_accuracy_is_one_half_for_a_constant_guess():
    labels = np.array([0] * 9 + [1])
    assert hv.accuracy(np.zeros(10), labels) == pytest.approx(0.5)  # 90% plain accuracy
    assert hv.accuracy(labels.astype(float), labels) == 1.0
    assert hv.accuracy(1.0 - labels, labels) == 0.0


def test_runs_end_to_end_on_a_small_dataset(split_fake_dataset, capsys):
    pytest.importorskip("torch")
    ds = split_fake_dataset
    assert hv.main([str(ds.root), "--steps", "3", "--batch", "4", "--crop", "16", "--min-side", "1",
                    "--min-offset", "0", "--max-occlusion", "3"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert re.fullmatch(r"heading_visibility: accuracy \d\.\d{3} on \d+ test crops \(chance 0\.5; train \d+\), "
                        r"ego (\d\.\d{3}|-), infrastructure (\d\.\d{3}|-), aerial (\d\.\d{3}|-)", last), last
