"""bench_realism.dair_camera: a roadside camera recovered from a DAIR-V2X label's own 2D and 3D boxes
(the sample has no calibration). The labels come from the converters' DAIR fixture
(omnigen.converters.dair_fixture), which projects each cuboid's corners with its own pinhole camera,
independently of bench_realism and omnigen.geometry, and returns that camera: the fit must give it
back. The fixture's frames also hold truncated objects (2D boxes clipped to the image), which the
fit has to leave out."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from benchmarks import bench_realism as br
from omnigen.converters.dair_fixture import IGNORE_NAMES, FixtureCamera, write_dair_tree


def _fixture_frame(root: Path, seed: int) -> tuple[list, list[dict], FixtureCamera]:
    """One fixture frame at DAIR-V2X's image size: (parsed labels, raw label JSON, its camera)."""
    fx = write_dair_tree(root, 1, seed=seed, image_size=br.DAIR_IMAGE, objects=(12, 14))
    folder = root / "label" / "camera"
    raw = json.loads((folder / f"{fx.keys[0]}.json").read_text())
    return br.dair_labels(folder), raw, fx.cameras[0]


@pytest.mark.parametrize("seed", [0, 7])
def test_the_fixture_camera_is_recovered_from_its_labels(tmp_path, seed):
    pytest.importorskip("scipy")
    labels, raw, truth = _fixture_frame(tmp_path, seed)
    untruncated = [o for o in raw if o["truncated_state"] == "0" and o["type"] not in IGNORE_NAMES]
    assert len(untruncated) < len(labels)  # the frame has truncated objects for the fit to leave out
    cam = br.dair_camera(labels)
    assert cam["boxes"] == len(untruncated) and cam["rms_px"] < 1.0
    assert cam["pitch_deg"] == pytest.approx(math.degrees(truth.pitch), abs=0.2)
    f = truth.K[1, 1]  # the fixture's fx is f within 0.2 %
    assert cam["hfov_deg"] == pytest.approx(2 * math.degrees(math.atan(br.DAIR_IMAGE[0] / 2 / f)), abs=0.3)
    assert cam["height_m"] == pytest.approx(truth.height, abs=0.1)
    vfov = 2 * math.degrees(math.atan(br.DAIR_IMAGE[1] / 2 / f))
    assert cam["top_edge_deg"] == pytest.approx(math.degrees(truth.pitch) - vfov / 2, abs=0.3)


def test_too_few_untruncated_boxes_give_no_camera(tmp_path):
    labels, _, _ = _fixture_frame(tmp_path, 0)
    kept = [o for o in labels if br.untruncated(o)]
    assert len(kept) >= 4 and br.dair_camera(kept[:3]) is None
    assert br.dair_camera(kept[:3] + [o for o in labels if not br.untruncated(o)]) is None
