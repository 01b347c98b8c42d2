"""benchmarks/crop_apart.py: variants of the crop stage's training scored on the same crops, on a
tiny fake dataset (the figures are meaningless; the plumbing is what is checked)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import crop_apart  # noqa: E402
from omnigen.detector.crop_train_config import CropTrainConfig  # noqa: E402


def test_variants_parse_into_configs_and_bad_ones_are_refused_by_name():
    name, cfg, split, position = crop_apart.parse_variant("flat:balance=0.5,class_gain=0.25,batch=8,split=0", 30,
                                                          copies=2)
    assert name == "flat" and cfg == CropTrainConfig(steps=30, balance=0.5, class_gain=0.25, batch=8, copies=2,
                                                     offset_gain=0.0)
    assert split is False and position is False
    # without the offset term unless asked, unlike train-crop: the variants written down before it
    assert crop_apart.parse_variant("default:", 7) == ("default", CropTrainConfig(steps=7, offset_gain=0.0), True, False)
    assert crop_apart.parse_variant("offset:offset_gain=0.3", 7)[1].offset_gain == 0.3
    assert crop_apart.parse_variant("where:position=1", 7)[3] is True
    assert crop_apart.parse_variant("half:amp=bf16", 7)[1].amp == "bf16"
    for bad, message in (("x:speed=2", "'speed' is not one of"), ("x:balance=much", "not a number"),
                         (":balance=0", "a name first"), ("x:balance=2", "balance"),
                         ("x:copies=2", "'copies' is not one of"), ("x:amp=fp8", "amp")):
        with pytest.raises(SystemExit, match=message):
            crop_apart.parse_variant(bad, 10)


def test_trains_each_variant_and_scores_it_beside_the_detectors_stage(split_fake_dataset, detector_checkpoint,
                                                                       tmp_path, capsys):
    weights = detector_checkpoint(tmp_path / "det.pt", 32, crop_classes=True)
    argv = [str(split_fake_dataset.root), str(weights), "--steps", "3", "--copies", "1",
            "--variant", "a:batch=8", "--variant", "b:batch=8,balance=0,heading_gain=0,position=1"]
    assert crop_apart.main(argv) == 0
    out = capsys.readouterr().out
    assert "the detector's stage" in out and "a: " in out and "b: " in out
    assert out.strip().splitlines()[-1].startswith("crop_apart: best layout rel ")
    with pytest.raises(SystemExit, match="share a name"):
        crop_apart.main([*argv[:-2], "--variant", "a:batch=4"])
    with pytest.raises(SystemExit, match="no crop stage"):
        crop_apart.main([str(split_fake_dataset.root), str(detector_checkpoint(tmp_path / "plain.pt", 0))])
