"""The record: round trips, and bad records rejected with the frame and the field named."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from omnigen.conventions import NUM_KEYPOINTS, V_OCCLUDED, V_OUTSIDE, V_VISIBLE
from omnigen.fakes import random_frame
from omnigen.formats.kitti import kitti_rotation
from omnigen.geometry import Box3D
from omnigen.record import FrameRecord, ObjectRecord, RecordError


@pytest.fixture()
def good() -> dict:
    rec = random_frame(seed=7, index=3, source="synthetic", view="infrastructure", n_objects=4)
    assert len(rec.objects) == 4
    return json.loads(json.dumps(rec.to_dict()))


def test_round_trip_is_lossless(good):
    rec = FrameRecord.from_dict(good)
    assert rec.to_dict() == good
    assert json.loads(json.dumps(rec.to_dict())) == good


def _reject(d: dict, field: str, words: str) -> RecordError:
    with pytest.raises(RecordError) as err:
        FrameRecord.from_dict(d, file="records/x.json")
    assert err.value.field == field, str(err.value)
    assert err.value.frame_id == d.get("frame_id")
    message = str(err.value)
    assert "records/x.json" in message and field in message and words in message
    return err.value


def test_nan_is_rejected(good):
    d = copy.deepcopy(good)
    d["objects"][1]["keypoints"][2][0] = float("nan")
    _reject(d, "objects[1].keypoints[2]", "NaN")
    d = copy.deepcopy(good)
    d["objects"][0]["box3d"]["center"][2] = float("inf")
    _reject(d, "objects[0].box3d.center", "NaN or infinity")
    d = copy.deepcopy(good)
    d["objects"][0]["truncation"] = float("nan")
    _reject(d, "objects[0].truncation", "not finite")


@pytest.mark.parametrize("field", ["category", "bbox", "keypoints", "box3d", "in_image", "truncation"])
def test_missing_object_field_is_rejected(good, field):
    d = copy.deepcopy(good)
    del d["objects"][2][field]
    _reject(d, f"objects[2].{field}", "missing")


@pytest.mark.parametrize("field", ["frame_id", "K", "width", "source", "view", "objects", "schema_version"])
def test_missing_frame_field_is_rejected(good, field):
    d = copy.deepcopy(good)
    del d[field]
    with pytest.raises(RecordError) as err:
        FrameRecord.from_dict(d)
    assert err.value.field == field and "missing" in str(err.value)


@pytest.mark.parametrize("count", [0, 7, 9])
def test_wrong_keypoint_count_is_rejected(good, count):
    d = copy.deepcopy(good)
    kp = d["objects"][0]["keypoints"]
    d["objects"][0]["keypoints"] = (kp * 2)[:count]
    _reject(d, "objects[0].keypoints", f"expected {NUM_KEYPOINTS} keypoints, got {count}")


def test_other_contract_violations(good):
    d = copy.deepcopy(good)
    d["objects"][0]["category"] = "spaceship"
    _reject(d, "objects[0].category", "not one of")
    d = copy.deepcopy(good)
    d["objects"][1]["instance_id"] = d["objects"][0]["instance_id"]
    _reject(d, "objects[1].instance_id", "duplicate")
    d = copy.deepcopy(good)
    d["objects"][0]["box3d"]["rotation"] = [[1, 0, 0], [0, 1, 0], [0, 0, -1]]
    _reject(d, "objects[0].box3d.rotation", "rotation")
    d = copy.deepcopy(good)
    d["view"] = "satellite"
    _reject(d, "view", "not one of")
    d = copy.deepcopy(good)
    d["synthetic"] = None
    _reject(d, "synthetic", "seed")
    d = copy.deepcopy(good)
    d["objects"][0]["bbox"] = [10, 10, 5, 20]
    _reject(d, "objects[0].bbox", "x2 < x1")
    d = copy.deepcopy(good)
    d["objects"][0]["keypoints"][0] = None  # null but not flagged behind the camera
    _reject(d, "objects[0].keypoints[0]", "not behind the camera")
    for bad in ("../outside.png", "/etc/passwd", "images/../../x.png", "C:/x.png"):
        d = copy.deepcopy(good)
        d["image"] = bad
        _reject(d, "image", "relative path inside the dataset")
    d = copy.deepcopy(good)
    d["synthetic"]["depth"] = "../depth.exr"
    _reject(d, "synthetic.depth", "relative path")
    d = copy.deepcopy(good)
    d["schema_version"] = 99
    _reject(d, "schema_version", "schema")


def test_visibility_follows_coco():
    K = np.array([[500.0, 0, 159.5], [0, 500.0, 95.5], [0, 0, 1]])
    # A car crossing the right image edge, half behind the near plane on one side.
    box = Box3D([3.0, 1.0, 8.0], [4.2, 1.8, 1.5], kitti_rotation(0.4))
    obj = ObjectRecord.from_box("car", 1, box, K, 320, 192)
    assert obj is not None
    v = obj.visibility
    for j in range(8):
        if not obj.in_image[j]:
            assert v[j] == V_OUTSIDE
        else:
            assert v[j] == (V_OCCLUDED if obj.occluded[j] else V_VISIBLE)
    assert (v == V_OUTSIDE).any() and (v > 0).any()


def _mutations(good: dict):
    """Copies of `good` with one object field broken (or oddly typed but valid) in many ways."""
    values = [None, "x", "0.5", True, 1, 0, -1, 2.0, 0.5, float("nan"), float("inf"), [], [1, 2], {},
              np.bool_(True), np.float64(0.5), (1.0, 2.0)]
    obj = good["objects"][1]
    for key in list(obj):
        for v in values:
            d = copy.deepcopy(good)
            d["objects"][1][key] = v
            yield d
        if isinstance(obj[key], list):
            for j in range(len(obj[key])):
                for v in values:
                    d = copy.deepcopy(good)
                    d["objects"][1][key][j] = v
                    yield d
    for part in ("center", "dims", "rotation"):
        for v in values + [[1.0, 2.0, 3.0, 4.0]]:
            d = copy.deepcopy(good)
            d["objects"][1]["box3d"][part] = v
            yield d
    for scale in (1.0 + 0.5e-4, 1.0 + 2e-4, -1.0):  # inside, just outside, and far outside the tolerance
        d = copy.deepcopy(good)
        d["objects"][1]["box3d"]["rotation"][0] = [x * scale for x in d["objects"][1]["box3d"]["rotation"][0]]
        yield d
    d = copy.deepcopy(good)
    d["objects"][1] = "not an object"
    yield d


def test_objects_checked_at_once_agree_with_one_by_one(good):
    """The stacked check never accepts what the per-object check refuses, and builds the same objects."""
    from omnigen.record import _FrameParser

    accepted = refused = 0
    for d in [good, *_mutations(good)]:
        parser = _FrameParser(d, None)
        try:
            expected = [parser.object(o, f"objects[{i}]") for i, o in enumerate(d["objects"])]
        except RecordError:
            expected = None
        at_once = parser.objects_at_once(d["objects"])
        if expected is None:
            assert at_once is None, d
            refused += 1
            continue
        if at_once is not None:
            accepted += 1
            assert [o.to_dict() for o in at_once] == [o.to_dict() for o in expected]
            for a, b in zip(at_once, expected):
                assert np.array_equal(a.keypoints, b.keypoints, equal_nan=True)
                assert a.bbox_source is None and b.bbox_source is None or np.array_equal(a.bbox_source, b.bbox_source)
    assert accepted > 20 and refused > 100  # both branches really exercised
