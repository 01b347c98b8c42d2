"""benchmarks/crop_classes.py: its AP is the ranking's, its crops keep the taxonomy's classes, its
frame draw follows the weights, and it runs end to end (the draw itself is crop_stage.draw_rows',
tested in tests/detector/test_crop_stage.py)."""

import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import crop_classes as cc  # noqa: E402
from benchmarks.crop_layout import LayoutCrops  # noqa: E402


def test_one_vs_rest_ap_is_the_precision_at_each_positive():
    positive = np.array([True, False, True, False])
    assert cc.one_vs_rest_ap(np.array([0.9, 0.1, 0.8, 0.2]), positive) == 1.0  # positives first
    # ranked: pos, neg, pos, neg -> precision 1 at the first, 2/3 at the second
    assert np.isclose(cc.one_vs_rest_ap(np.array([0.9, 0.8, 0.7, 0.1]), positive), (1 + 2 / 3) / 2)
    assert np.isnan(cc.one_vs_rest_ap(np.array([0.5, 0.4]), np.array([False, False])))


def test_crops_of_classes_the_taxonomy_drops_are_left_out():
    from omnigen.taxonomy import load_taxonomy

    n = 3
    crops = LayoutCrops(images=np.zeros((n, 16, 16, 3), np.uint8), boxes=np.zeros((n, 4)), true_boxes=np.zeros((n, 4)),
                        keypoints=np.zeros((n, 8, 2)), labelled=np.ones((n, 8), bool), views=np.zeros(n, np.int64),
                        classes=np.array(["bus", "not-a-class", "car"], dtype=object), frames=np.arange(n))
    taxonomy = load_taxonomy("fine")
    kept, ids = cc.labelled(crops, taxonomy)
    assert list(kept.classes) == ["bus", "car"] and list(kept.frames) == [0, 2]
    assert list(ids) == [taxonomy.classes.index("bus"), taxonomy.classes.index("car")]


def test_frame_batches_are_distinct_frames_drawn_by_weight():
    frames = np.arange(10)
    weights = np.array([10.0] + [1.0] * 9)
    batches = cc.frame_batches(frames, weights, 3, 2000, np.random.default_rng(0))
    assert all(len(set(b.tolist())) == 3 for b in batches)
    share = np.mean([0 in b for b in batches])
    assert share > 0.6  # a frame of weight 10 among nine of 1 is in most batches of 3; uniformly it would be 0.3


def test_runs_end_to_end_on_a_small_dataset(split_fake_dataset, capsys):
    pytest.importorskip("torch")
    ds = split_fake_dataset
    assert cc.main([str(ds.root), "--steps", "3", "--batch-frames", "4", "--crop", "16"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert re.fullmatch(r"crop_classes: mean AP uniform \d\.\d{3}, balanced \d\.\d{3}; rare-class named "
                        r"uniform (\d\.\d{2}|nan), balanced (\d\.\d{2}|nan) \(\d+ classes under 200 train objects\)",
                        out[-1]), out[-1]
    assert any(line.startswith("uniform: 3 steps") for line in out)
    with pytest.raises(SystemExit, match="multiple of 16"):
        cc.main([str(ds.root), "--crop", "20"])
