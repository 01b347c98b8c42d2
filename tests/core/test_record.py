"""The record: round trips, and bad records rejected with the frame and the field named."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from omnigen.conventions import NUM_KEYPOINTS, V_OCCLUDED, V_OUTSIDE, V_VISIBLE
from omnigen.fakes import random_frame, schema1_bytes
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
    for key in ("track_id", "velocity"):  # required in schema 2, refused in schema 1
        d = copy.deepcopy(good)
        if key in d["objects"][1]:
            del d["objects"][1][key]
        else:
            d["objects"][1][key] = None
        yield d


@pytest.fixture(params=["schema2", "sequence", "schema1"])
def any_good(request, good) -> tuple[dict, int]:
    """A valid record of each kind the stacked check reads: schema 2 with null or filled sequence
    and track fields, and schema 1 (no such keys); with its schema version."""
    if request.param == "schema2":
        return good, 2
    rec = random_frame(seed=7, index=3, source="synthetic", view="infrastructure", n_objects=4, sequence=True)
    if request.param == "sequence":
        return json.loads(json.dumps(rec.to_dict())), 2
    return json.loads(schema1_bytes(rec)), 1


def test_objects_checked_at_once_agree_with_one_by_one(any_good):
    """The stacked check never accepts what the per-object check refuses, and builds the same objects."""
    from omnigen.record import _FrameParser

    good, version = any_good
    accepted = refused = 0
    for d in [good, *_mutations(good)]:
        parser = _FrameParser(d, None)
        parser.version = version
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


# -- schema 2: sequences, pairs, poses and tracks ---------------------------------------------

@pytest.fixture()
def sequenced() -> dict:
    rec = random_frame(seed=7, index=13, source="synthetic", view="ego", n_objects=4, sequence=True)
    assert rec.sequence and rec.camera_to_world is not None and all(o.track_id for o in rec.objects)
    return json.loads(json.dumps(rec.to_dict()))


def test_schema2_round_trip(sequenced):
    rec = FrameRecord.from_dict(sequenced)
    assert rec.to_dict() == sequenced and rec.schema_version == 2
    assert (rec.sequence, rec.timestamp, rec.pair) == ("synthetic-seq001", 0.3, "synthetic-seq001-pair000001")
    assert np.array_equal(rec.camera_to_world, sequenced["camera_to_world"])
    assert [o.track_id for o in rec.objects] == [301, 302, 303, 304]  # frame 3 of its sequence: 300 + instance id
    assert np.array_equal(rec.objects[2].velocity, sequenced["objects"][2]["velocity"])


def test_schema2_requires_its_keys_nullable(good, sequenced):
    for key in ("sequence", "timestamp", "pair", "camera_to_world"):
        assert good[key] is None
        d = copy.deepcopy(sequenced)
        del d[key]
        _reject(d, key, "missing")
    for key in ("track_id", "velocity"):
        assert good["objects"][0][key] is None
        d = copy.deepcopy(sequenced)
        del d["objects"][3][key]
        _reject(d, f"objects[3].{key}", "missing")


def test_schema1_still_reads(sequenced):
    d = json.loads(schema1_bytes(FrameRecord.from_dict(sequenced)))
    assert d["schema_version"] == 1 and "sequence" not in d and "track_id" not in d["objects"][0]
    rec = FrameRecord.from_dict(d)
    assert rec.schema_version == 1 and rec.sequence is rec.timestamp is rec.pair is rec.camera_to_world is None
    assert all(o.track_id is None and o.velocity is None for o in rec.objects)
    upgraded = rec.to_dict()  # written again, a schema-1 record is schema 2 with the new fields null
    assert upgraded["schema_version"] == 2 and upgraded["camera_to_world"] is None
    assert FrameRecord.from_dict(upgraded).to_dict() == upgraded
    d["objects"][1]["track_id"] = 5
    _reject(d, "objects[1].track_id", "not in schema 1")
    d = json.loads(schema1_bytes(rec))
    d["sequence"] = "s"
    _reject(d, "sequence", "not in schema 1")


def test_camera_to_world_checked(sequenced):
    def with_pose(change) -> dict:
        d = copy.deepcopy(sequenced)
        m = np.array(d["camera_to_world"])
        change(m)
        d["camera_to_world"] = m.tolist()
        return d

    _reject(with_pose(lambda m: m.__setitem__((0, 0), m[0, 0] * 1.001)), "camera_to_world", "rotation part not orthonormal")
    _reject(with_pose(lambda m: m.__setitem__((slice(0, 3), 0), -m[:3, 0])), "camera_to_world", "determinant")
    _reject(with_pose(lambda m: m.__setitem__((3, 0), 0.5)), "camera_to_world", "last row must be 0 0 0 1")
    _reject(with_pose(lambda m: m.__setitem__((3, 3), 2.0)), "camera_to_world", "last row must be 0 0 0 1")
    _reject(with_pose(lambda m: m.__setitem__((1, 3), float("nan"))), "camera_to_world", "NaN")
    d = copy.deepcopy(sequenced)
    d["camera_to_world"] = d["camera_to_world"][:3]
    _reject(d, "camera_to_world", "shape")
    ok = with_pose(lambda m: m.__setitem__((0, 3), 3.4e6))  # a map-projected world is fine here
    assert FrameRecord.from_dict(ok).camera_to_world[0, 3] == 3.4e6


def test_duplicate_track_id_named(sequenced):
    d = copy.deepcopy(sequenced)
    d["objects"][2]["track_id"] = d["objects"][0]["track_id"]
    err = _reject(d, "objects[2].track_id", f"duplicate track_id {d['objects'][0]['track_id']}")
    assert str(err).count("\n") == 0  # one line
    d["objects"][0]["track_id"] = d["objects"][2]["track_id"] = None  # null is no track: two may be null
    assert FrameRecord.from_dict(d).objects[0].track_id is None
    for bad in (0, -3, 1.5, "7", True):
        d = copy.deepcopy(sequenced)
        d["objects"][1]["track_id"] = bad
        _reject(d, "objects[1].track_id", "integer" if not isinstance(bad, int) or bad is True else "outside")


def test_sequence_fields_checked(sequenced):
    d = copy.deepcopy(sequenced)
    d["sequence"] = None
    _reject(d, "timestamp", "'sequence' is null")
    d["timestamp"] = None
    assert FrameRecord.from_dict(d).sequence is None  # no sequence, no clock: fine
    for key, bad, words in (("timestamp", -0.1, "outside"), ("timestamp", "0.1", "expected a number"),
                            ("sequence", "a b/c", "letters, digits"), ("pair", "", "non-empty string"),
                            ("pair", 3, "non-empty string")):
        d = copy.deepcopy(sequenced)
        d[key] = bad
        _reject(d, key, words)
    d = copy.deepcopy(sequenced)
    d["objects"][0]["velocity"] = [1.0, float("inf"), 0.0]
    _reject(d, "objects[0].velocity", "NaN or infinity")


def test_fast_parser_takes_track_fields(sequenced, monkeypatch):
    """Records with tracks, velocities and null ones are read by the stacked check: falling back to
    the per-object check for every such record would silently cost most of a read's time."""
    from omnigen.record import _FrameParser

    d = copy.deepcopy(sequenced)
    d["objects"][1]["track_id"] = d["objects"][1]["velocity"] = None
    parser = _FrameParser(d, None)
    objects = parser.objects_at_once(d["objects"])
    assert objects is not None
    assert [o.track_id for o in objects] == [301, None, 303, 304]
    assert objects[1].velocity is None
    assert np.array_equal(objects[3].velocity, d["objects"][3]["velocity"])

    def no_slow_path(self, o, path):
        raise AssertionError(f"{path} read one by one")

    monkeypatch.setattr(_FrameParser, "object", no_slow_path)
    assert FrameRecord.from_dict(d).to_dict() == d
    assert FrameRecord.from_dict(json.loads(schema1_bytes(FrameRecord.from_dict(d)))).objects[0].track_id is None
