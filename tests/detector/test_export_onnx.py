"""`omnigen export onnx`: the checkpoint's training size by default, and dynamic height and width."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx", reason="torch.onnx.export (dynamo=False) needs the 'onnx' package")
ort = pytest.importorskip("onnxruntime", reason="the export's check runs ONNX Runtime")

from omnigen.detector.model.checkpoint import save_checkpoint  # noqa: E402
from omnigen.detector.model.network import DetectorConfig, KeypointDetector  # noqa: E402
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
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx"]  # no crop stage, no second graph
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


def test_heading_aware_models_export_with_their_decode(tmp_path):
    """The layout's turn (the predicted image heading against the layout's own) is decided inside
    the graph: ONNX Runtime gives PyTorch's corners."""
    from omnigen.detector.prediction.export_onnx import export, max_difference

    torch.manual_seed(1)
    cfg = DetectorConfig("n", "c3k2", p2=False, num_classes=2, width=0.0625, depth=0.33, max_channels=64,
                         kpt_heading=True)
    model = KeypointDetector(cfg).eval()
    path = tmp_path / "m.onnx"
    export(model, path, 64)
    assert max_difference(model, path, 64) < 1e-4


def test_crop_stage_model_exports_its_crop_stage_beside(tmp_path, capsys):
    """A crop-stage model writes FILE-crops.onnx too; ONNX Runtime places the corners as PyTorch does
    at the traced size and, with --dynamic, at another, for any number of detections."""
    import numpy as np

    from omnigen.detector.prediction.export_onnx import crop_stage_max_difference, crop_stage_path
    from omnigen.detector.model.crop_stage import RefineWrapper, to_crop_units

    torch.manual_seed(2)
    cfg = DetectorConfig("n", "c3k2", p2=False, num_classes=2, width=0.0625, depth=0.33, max_channels=64,
                         kpt_heading=True, heading_crop=32)
    model = KeypointDetector(cfg).eval()
    with torch.no_grad():  # batch-norm statistics of real activations, so that the crops' outputs differ
        for m in model.crop_net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.momentum = None
        model.crop_net.train()(torch.rand(16, 3, 32, 32))
        model.crop_net.eval()
    ckpt = tmp_path / "best.pt"
    save_checkpoint(ckpt, {"config": cfg.to_dict(), "model": model.state_dict(), "classes": ["car", "bus"],
                           "train_config": {"imgsz": 64}})
    out = tmp_path / "m.onnx"
    assert main(["export", "onnx", str(ckpt), "--out", str(out), "--dynamic"]) == 0
    stage = crop_stage_path(out)
    assert stage.name == "m-crops.onnx" and stage.is_file() and "crop stage" in capsys.readouterr().out
    for size in (64, (96, 160)):
        assert crop_stage_max_difference(model, stage, size, seed=3) < 1e-4
    # and the layouts it places differ from crop to crop (the check would pass for a constant graph)
    rng = np.random.default_rng(0)
    boxes = torch.tensor([[4.0, 4.0, 40.0, 30.0]] * 6) + torch.from_numpy(rng.random((6, 1), dtype=np.float32) * 20)
    kpts = torch.from_numpy(rng.random((6, 8, 3), dtype=np.float32) * 60)
    x = torch.from_numpy(rng.random((1, 3, 64, 64), dtype=np.float32))
    with torch.no_grad():
        got = RefineWrapper(model.crop_net, 32)(x, boxes, kpts)
    layouts = to_crop_units(got[..., :2], boxes)
    assert float(layouts.std(0).max()) > 1e-3


@pytest.mark.parametrize("split", [False, True])
def test_a_class_naming_crop_stage_exports_its_class_probabilities(tmp_path, split):
    """With crop_classes the stage's graph has a second output, class_probs (N, nc), as PyTorch gives
    it; a stage whose classes come from a net of their own (crop_split, as omnigen train-crop writes
    it) exports as one graph with the same two outputs."""
    import onnxruntime as ort

    from omnigen.detector.prediction.export_onnx import crop_stage_max_difference, export_crop_stage

    torch.manual_seed(3)
    cfg = DetectorConfig("n", "c3k2", p2=False, num_classes=2, width=0.0625, depth=0.33, max_channels=64,
                         kpt_heading=True, heading_crop=32, crop_classes=True, crop_split=split)
    model = KeypointDetector(cfg).eval()
    with torch.no_grad():
        (model.crop_net.classes if split else model.crop_net).out.bias[-2:] = torch.tensor([0.3, -0.4])
    path = tmp_path / "m-crops.onnx"
    export_crop_stage(model, path, 64)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [o.name for o in sess.get_outputs()] == ["refined", "class_probs"]
    assert crop_stage_max_difference(model, path, 64, seed=1) < 1e-4


def test_a_stage_told_where_its_crops_were_exports_and_places_as_pytorch_at_any_size(tmp_path):
    """crop_position reads the input's size from the graph, so a --dynamic export traced at one
    size tells the net the right positions at another."""
    from omnigen.detector.prediction.export_onnx import crop_stage_max_difference, export_crop_stage

    torch.manual_seed(6)
    cfg = DetectorConfig("n", "c3k2", p2=False, num_classes=2, width=0.0625, depth=0.33, max_channels=64,
                         kpt_heading=True, heading_crop=32, crop_classes=True, crop_split=True, crop_position=True)
    model = KeypointDetector(cfg).eval()
    with torch.no_grad():  # the position's weights large, so that a wrong position would show
        model.crop_net.corners.hidden[0].weight[:, -3:] *= 50
    path = tmp_path / "m-position.onnx"
    export_crop_stage(model, path, 64, dynamic=True)
    for size in (64, (96, 160)):
        assert crop_stage_max_difference(model, path, size, seed=1) < 1e-4
