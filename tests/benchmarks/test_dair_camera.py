"""bench_realism.dair_camera: a roadside camera recovered from a DAIR-V2X label's own 2D and 3D boxes
(the sample has no calibration): a label made by a known camera gives that camera back."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from benchmarks import bench_realism as br


def _label(f: float, pitch: float, yaw: float, pos) -> list[dict]:
    """Cars on the ground ahead of a camera (DAIR's virtual-LiDAR frame, z up), their 2d_box the
    projection of their cuboids by that camera into a 1920 x 1080 image."""
    rng = np.random.default_rng(4)
    cp, sp, cw, sw = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    ahead, down, right = np.array([cp * cw, cp * sw, -sp]), np.array([-sp * cw, -sp * sw, -cp]), np.array([sw, -cw, 0.0])
    out = []
    for _ in range(9):
        d, side, rot = rng.uniform(20, 90), rng.uniform(-0.25, 0.25), rng.uniform(-math.pi, math.pi)
        l, w, h = rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.6)
        c = np.array([pos[0] + d * math.cos(yaw + side), pos[1] + d * math.sin(yaw + side), h / 2])
        s = np.array([[a, b, e] for a in (-1, 1) for b in (-1, 1) for e in (-1, 1)]) * [l / 2, w / 2, h / 2]
        pts = c + np.stack([math.cos(rot) * s[:, 0] - math.sin(rot) * s[:, 1], math.sin(rot) * s[:, 0] + math.cos(rot) * s[:, 1], s[:, 2]], 1)
        rel = pts - np.asarray(pos)
        u, v = 960 + f * (rel @ right) / (rel @ ahead), 540 + f * (rel @ down) / (rel @ ahead)
        out.append({"type": "Car", "truncated_state": "0", "occluded_state": "0", "alpha": "0",
                    "2d_box": {"xmin": u.min(), "ymin": v.min(), "xmax": u.max(), "ymax": v.max()},
                    "3d_dimensions": {"h": h, "w": w, "l": l}, "3d_location": {"x": c[0], "y": c[1], "z": c[2]},
                    "rotation": rot})
    return out


def test_a_known_camera_is_recovered_from_its_labels(tmp_path):
    pytest.importorskip("scipy")
    (tmp_path / "label").mkdir()
    (tmp_path / "label" / "000001.json").write_text(json.dumps(_label(2000.0, math.radians(18.0), math.radians(5.0), (1.0, -3.0, 7.5))))
    cam = br.dair_camera(tmp_path)
    assert cam["boxes"] == 9 and cam["rms_px"] < 0.5
    assert cam["pitch_deg"] == pytest.approx(18.0, abs=0.2)
    assert cam["hfov_deg"] == pytest.approx(2 * math.degrees(math.atan(960 / 2000.0)), abs=0.3)
    assert cam["height_m"] == pytest.approx(7.5, abs=0.1)
    assert cam["top_edge_deg"] == pytest.approx(18.0 - math.degrees(math.atan(540 / 2000.0)), abs=0.3)


def test_too_few_boxes_give_no_camera(tmp_path):
    (tmp_path / "label").mkdir()
    (tmp_path / "label" / "000001.json").write_text(json.dumps(_label(2000.0, 0.3, 0.0, (0.0, 0.0, 6.0))[:3]))
    assert br.dair_camera(tmp_path) is None
