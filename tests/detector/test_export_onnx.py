"""`omnigen export onnx`: the checkpoint's training size by default, and dynamic height and width."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx", reason="torch.onnx.export (dynamo=False) needs the 'onnx' package")
ort = pytest.importorskip("onnxruntime", reason="the export's check runs ONNX Runtime")

from omnigen.detector.checkpoint import save_checkpoint  # noqa: E402
from omnigen.detector.model import DetectorConfig, KeypointDetector  # noqa: E402
from omnigen.cli import main  # noqa: E402

TRAINED = 256


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A tiny model's checkpoint that says it was trained at 256 pixels."""
    torch.manual_seed(0)
    cfg = DetectorConfig("n", "c3k2", p2=False, num_classes=2, width=0.0625, depth=0.33, max_channels=64)
    model = KeypointDetector(cfg).eval()
    path = tmp_path_factory.mktemp("run") / "best.pt"
    save_checkpoint(path, {"config": cfg.to_dict(), "model": model.state_dict(), "classes": ["car", "bus"],
                           "train_config": {"imgsz": TRAINED}})
    return path


def _input_dims(path) -> list:
    dims = onnx.load(str(path)).graph.input[0].type.tensor_type.shape.dim
    return [d.dim_param or d.dim_value for d in dims]


def test_default_size_is_the_training_size(checkpoint, tmp_path, capsys):
    out = tmp_path / "m.onnx"
    assert main(["export", "onnx", str(checkpoint), "--out", str(out)]) == 0
    assert _input_dims(out) == [1, 3, TRAINED, TRAINED]
    assert f"1x3x{TRAINED}x{TRAINED}" in capsys.readouterr().out
    # an explicit --imgsz still wins
    assert main(["export", "onnx", str(checkpoint), "--out", str(out), "--imgsz", "128", "--no-check"]) == 0
    assert _input_dims(out) == [1, 3, 128, 128]


def test_dynamic_height_and_width(checkpoint, tmp_path):
    import numpy as np

    out = tmp_path / "d.onnx"
    assert main(["export", "onnx", str(checkpoint), "--out", str(out), "--dynamic"]) == 0  # checks two sizes
    assert _input_dims(out) == [1, 3, "height", "width"]
    sess = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    for h, w in ((TRAINED, TRAINED), (96, 160)):
        x = np.zeros((1, 3, h, w), dtype=np.float32)
        got = sess.run(None, {"images": x})[0]
        assert got.shape[2] == (h // 8) * (w // 8) + (h // 16) * (w // 16) + (h // 32) * (w // 32)


@pytest.mark.parametrize("order", ["kpt_turn", "kpt_heading"])
def test_turn_and_heading_aware_models_export_with_their_decode(order, tmp_path):
    """The layout's turn (a logit, or the predicted image heading against the layout's own) is
    decided inside the graph: ONNX Runtime gives PyTorch's corners."""
    from omnigen.detector.export_onnx import export, max_difference

    torch.manual_seed(1)
    cfg = DetectorConfig("n", "c3k2", p2=False, num_classes=2, width=0.0625, depth=0.33, max_channels=64,
                         **{order: True})
    model = KeypointDetector(cfg).eval()
    path = tmp_path / "m.onnx"
    export(model, path, 64)
    assert max_difference(model, path, 64) < 1e-4
