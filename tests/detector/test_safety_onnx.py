"""Issue 44, hole 7: `omnigen export onnx RUN/last.pt --out RUN/last.pt` replaced the checkpoint.
The export writes only a new file or one it wrote before (marked in its first bytes), never its
input, and checks both graphs of a crop-stage model before writing either."""

from __future__ import annotations

import os

import pytest

pytest.importorskip("torch")
onnx = pytest.importorskip("onnx", reason="torch.onnx.export (dynamo=False) needs the 'onnx' package")

from omnigen.cli import main  # noqa: E402


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    return err


def test_export_onnx_never_writes_onto_its_checkpoint(detector_checkpoint, tmp_path, capsys):
    weights = detector_checkpoint(tmp_path / "run" / "last.pt", 0)
    before = weights.read_bytes()
    assert main(["export", "onnx", str(weights), "--out", str(weights), "--no-check"]) == 1
    assert f"is {weights}" in _error_line(capsys)
    # nor through another name of the same file (a hard link)
    alias = tmp_path / "alias.onnx"
    os.link(weights, alias)
    assert main(["export", "onnx", str(weights), "--out", str(alias), "--no-check"]) == 1
    assert "reads; refusing to write onto an input" in _error_line(capsys)
    assert weights.read_bytes() == before


def test_export_onnx_replaces_only_a_file_it_wrote(detector_checkpoint, tmp_path, capsys):
    weights = detector_checkpoint(tmp_path / "best.pt", 0)
    mine = tmp_path / "model.onnx"
    mine.write_bytes(b"someone's own model")
    assert main(["export", "onnx", str(weights), "--out", str(mine), "--imgsz", "64", "--no-check"]) == 1
    assert "was not written by 'omnigen export onnx'" in _error_line(capsys)
    assert mine.read_bytes() == b"someone's own model"

    out = tmp_path / "m.onnx"
    for _ in range(2):  # a rerun replaces its own file
        assert main(["export", "onnx", str(weights), "--out", str(out), "--imgsz", "64", "--no-check"]) == 0
    model = onnx.load(str(out))  # the mark written first is read back as the model's metadata
    assert {p.key: p.value for p in model.metadata_props} == {"omnigen": "export onnx"}
    onnx.checker.check_model(model)


def test_a_crop_stage_file_of_someone_else_stops_the_export_before_either_graph(detector_checkpoint, tmp_path, capsys):
    weights = detector_checkpoint(tmp_path / "crop.pt", 32)
    out = tmp_path / "m.onnx"
    (tmp_path / "m-crops.onnx").write_bytes(b"not ours")
    assert main(["export", "onnx", str(weights), "--out", str(out), "--imgsz", "64", "--no-check"]) == 1
    assert "m-crops.onnx: exists and was not written by" in _error_line(capsys)
    assert not out.exists() and (tmp_path / "m-crops.onnx").read_bytes() == b"not ours"


@pytest.mark.parametrize("value", ["0", "-64", "100000"])
def test_imgsz_is_checked_when_parsed(value, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["export", "onnx", str(tmp_path / "w.pt"), "--out", str(tmp_path / "m.onnx"), "--imgsz", value])
    assert exc.value.code == 2
    assert "argument --imgsz" in capsys.readouterr().err
