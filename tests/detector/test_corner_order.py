"""detector/evaluation/corner_order.py: which corner order fits box-matched predictions (heading confusion)."""

from __future__ import annotations

import numpy as np

from omnigen.detector.evaluation.corner_order import ORDERS, corner_order_counts
from omnigen.conventions import CORNER_SIGNS, TURN_IDX
from omnigen.fakes import write_fake_dataset


def _predictions(ds, order_of):
    """One prediction per object (box as labelled, corners in the order order_of(row) names)."""
    o, out = ds.objects, []
    for f, fid in enumerate(ds.table.frame_id):
        for r in range(int(ds.offsets[f]), int(ds.offsets[f + 1])):
            x1, y1, x2, y2 = o.bbox[r].tolist()
            order = ORDERS[order_of(r)]
            kp = np.zeros((8, 3))
            kp[list(order), :2] = o.keypoints[r]  # prediction corner order[i] holds true corner i
            out.append({"frame_id": fid, "bbox": [x1, y1, x2 - x1, y2 - y1], "score": 0.9,
                        "keypoints": np.nan_to_num(kp).ravel().tolist(), "category_id": 1})
    return out


def test_turn_idx_is_a_half_turn_of_the_corner_signs():
    turned = CORNER_SIGNS * [-1, -1, 1]  # 180 degrees about z: x and y change sign
    np.testing.assert_array_equal(CORNER_SIGNS[list(TURN_IDX)], turned)


def test_counts_the_order_each_prediction_was_made_in(tmp_path):
    ds = write_fake_dataset(tmp_path / "ds", n_frames=5, objects_per_frame=4, seed=1)
    front = ~ds.objects.behind_camera.any(axis=1)
    names = ["as labelled", "turned 180", "mirrored"]
    pick = lambda r: names[r % 3]  # noqa: E731
    counts = corner_order_counts(ds, _predictions(ds, pick), split=None)
    expected = {n: int(sum(front[r] and pick(r) == n for r in range(len(front)))) for n in names}
    assert counts.matched == int(front.sum()) and counts.unmatched == 0
    for n in names:
        assert counts.best[n] == expected[n], n
    assert counts.fraction("turned 180") == expected["turned 180"] / counts.matched
    # low scores are not matched at all
    faint = [{**p, "score": 0.1} for p in _predictions(ds, pick)]
    none = corner_order_counts(ds, faint, split=None)
    assert none.matched == 0 and none.unmatched == int(front.sum())
