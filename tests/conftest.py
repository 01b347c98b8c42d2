"""Fixtures shared across the test folders: a tiny detector checkpoint and a fake dataset with splits."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist (make test runs one worker per core), each worker's torch, OpenMP and
    BLAS get the cores divided among the workers: torch's default of one thread per core in every
    worker would run twice as many threads as cores, and OpenMP's busy-waiting then costs more than
    the second thread gives. Set before any test module imports torch (the environment is read at
    its first import); a test that wants a thread count sets it itself."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        threads = str(max(1, (os.cpu_count() or 1) // workers))
        for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            os.environ.setdefault(name, threads)


TINY = dict(width=0.0625, depth=0.33, max_channels=64)
"""A detector small enough to build in a test."""


def _save_checkpoint(path: Path, heading_crop: int, crop_classes: bool = False) -> Path:
    import torch

    from omnigen.detector.model.checkpoint import save_checkpoint
    from omnigen.detector.model.network import DetectorConfig, KeypointDetector
    from omnigen.taxonomy import load_taxonomy

    torch.manual_seed(0)
    classes = list(load_taxonomy("fine").classes)
    cfg = DetectorConfig(num_classes=len(classes), kpt_heading=True, heading_crop=heading_crop,
                         crop_classes=crop_classes, **TINY)
    save_checkpoint(path, {"config": cfg.to_dict(), "model": KeypointDetector(cfg).state_dict(), "classes": classes})
    return path


@pytest.fixture
def detector_checkpoint():
    """checkpoint(path, heading_crop, crop_classes=False) -> path: an untrained tiny detector saved
    as `omnigen train` saves one (fine taxonomy, the heading head; a crop stage of that side where
    heading_crop > 0), for the tests that read a crop-stage checkpoint."""
    return _save_checkpoint


@pytest.fixture
def split_fake_dataset(tmp_path):
    """A fake merged dataset of 12 frames, 6 objects each, its first 9 frames the train split and
    the last 3 the test split: what the crop-stage tests and omnigen train-crop read."""
    from omnigen.fakes import write_fake_dataset
    from omnigen.splits import write_split

    ds = write_fake_dataset(tmp_path / "ds", 12, objects_per_frame=6, seed=4)
    ids = [ds.frames[i]["frame_id"] for i in range(len(ds))]
    write_split(ds.root, "train", ids[:9])
    write_split(ds.root, "test", ids[9:])
    return ds
