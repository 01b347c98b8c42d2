"""The COCO export carries the sequence, pair, pose and track fields where a frame has them, and
adds nothing for data without them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from omnigen.fakes import fake_cooperative_records, write_cooperative_dataset, write_fake_dataset
from omnigen.formats.coco import export_coco

LEGACY_IMAGE_KEYS = {"id", "file_name", "width", "height", "frame_id", "source", "view", "K", "ignore_regions",
                     "depth_file", "instance_file"}
LEGACY_ANNOTATION_KEYS = {"id", "image_id", "category_id", "fine_category", "bbox", "area", "iscrowd", "keypoints",
                          "num_keypoints", "instance_id", "box3d", "truncation", "occlusion_level"}


def test_data_without_sequences_exports_as_before(tmp_path):
    """A schema-1 dataset and the same frames written as schema 2 (fields null) give the same
    bytes, with the keys an export had before schema 2 and no others."""
    files = []
    for schema in (1, 2):
        ds = write_fake_dataset(tmp_path / f"s{schema}", n_frames=6, objects_per_frame=3, seed=3, schema=schema)
        files.append(tmp_path / f"s{schema}.json")
        export_coco(ds, files[-1])
    assert files[0].read_bytes() == files[1].read_bytes()
    coco = json.loads(files[0].read_bytes())
    assert coco["annotations"] and all(set(im) == LEGACY_IMAGE_KEYS for im in coco["images"])
    assert all(set(a) <= LEGACY_ANNOTATION_KEYS for a in coco["annotations"])


def test_sequence_pair_pose_and_tracks_are_exported(tmp_path):
    records = fake_cooperative_records(seed=2, n_sequences=1, n_instants=2, n_objects=3)
    ds = write_cooperative_dataset(tmp_path / "coop", records)
    export_coco(ds, tmp_path / "coop.json")
    coco = json.loads((tmp_path / "coop.json").read_bytes())
    by_id = {r.frame_id: r for r in records}
    for image in coco["images"]:
        rec = by_id[image["frame_id"]]
        assert (image["sequence"], image["timestamp"]) == (rec.sequence, rec.timestamp)
        assert image.get("pair") == rec.pair  # the aerial frames have none: no key
        assert np.array_equal(image["camera_to_world"], rec.camera_to_world)
        anns = [a for a in coco["annotations"] if a["image_id"] == image["id"]]
        assert [a["track_id"] for a in anns] == [o.track_id for o in rec.objects]
        assert all(np.array_equal(a["velocity"], o.velocity) for a, o in zip(anns, rec.objects))
    assert any("pair" not in image for image in coco["images"])


def test_pycocotools_loads_the_sequence_export(tmp_path):
    coco_api = pytest.importorskip("pycocotools.coco")
    ds = write_cooperative_dataset(tmp_path / "coop", seed=1, n_sequences=1, n_instants=1, n_objects=2)
    export_coco(ds, tmp_path / "coop.json")
    api = coco_api.COCO(str(tmp_path / "coop.json"))
    assert len(api.getImgIds()) == 3 and len(api.getAnnIds()) == 6
