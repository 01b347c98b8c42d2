"""Fixtures the benchmark scripts' tests share."""

from __future__ import annotations

import pytest


@pytest.fixture
def split_fake_dataset(tmp_path):
    """A fake merged dataset of 12 frames, 6 objects each, its first 9 frames the train split and
    the last 3 the test split: what the crop benchmarks (crop_layout, heading_visibility,
    crop_classes) read."""
    from omnigen.fakes import write_fake_dataset
    from omnigen.splits import write_split

    ds = write_fake_dataset(tmp_path / "ds", 12, objects_per_frame=6, seed=4)
    ids = [ds.frames[i]["frame_id"] for i in range(len(ds))]
    write_split(ds.root, "train", ids[:9])
    write_split(ds.root, "test", ids[9:])
    return ds
