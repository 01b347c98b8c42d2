"""Issue 24: the device-side NMS (omnigen.detector.prediction.nms.greedy_survivors) keeps exactly what the host loop keeps."""

from __future__ import annotations

import numpy as np
import torch

from omnigen.detector.model.boxes import box_iou_pairwise as box_iou
from omnigen.detector.prediction.nms import greedy_survivors, nms


def test_matrix_nms_keeps_what_the_greedy_loop_keeps():
    rng = np.random.default_rng(0)
    for trial in range(30):
        n = int(rng.integers(1, 300))
        xy = torch.from_numpy(rng.uniform(0, 200, (n, 2))).float()
        wh = torch.from_numpy(rng.uniform(5, 60, (n, 2))).float()
        boxes = torch.cat([xy, xy + wh], 1)
        scores = torch.from_numpy(rng.uniform(0, 1, n)).float()
        want = nms(boxes, scores, 0.5)  # the CPU path: the loop over the host matrix
        order = scores.argsort(descending=True)
        sorted_boxes = boxes[order]
        got = order[greedy_survivors(box_iou(sorted_boxes, sorted_boxes) > 0.5)]
        assert torch.equal(got, want), trial
    # a chain: each box overlaps the next (IoU 0.25), so survival alternates down the chain
    boxes = torch.tensor([[i * 6.0, 0.0, i * 6.0 + 10.0, 10.0] for i in range(7)])
    assert nms(boxes, torch.linspace(1, 0.1, 7), 0.2).tolist() == [0, 2, 4, 6]
    keep = greedy_survivors(box_iou(boxes, boxes) > 0.2)
    assert keep.nonzero().squeeze(1).tolist() == [0, 2, 4, 6]
