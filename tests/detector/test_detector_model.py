"""The detector model: shapes and anchors per level option, both backbone families, every scale,
decoding, config round-trip and errors, gradients, train/eval behaviour, FLOP counting, ONNX export."""

from __future__ import annotations

import importlib.util
import warnings

import numpy as np
import pytest
import torch
from torch import nn

from omnigen.detector.model.backbones import BACKBONES, build_backbone
from omnigen.detector.model.network import (SCALE_NAMES, DetectorConfig, InferenceWrapper, KeypointDetector, count_parameters,
                            gflops)
from omnigen.detector.model.outputs import REG_MAX, HeadOutput
from omnigen.conventions import NUM_KEYPOINTS

TINY = dict(width=0.0625, depth=0.33, max_channels=64)


def tiny(backbone: str = "c3k2", p2: bool = True, p6: bool = False, nc: int = 3) -> KeypointDetector:
    torch.manual_seed(0)
    return KeypointDetector(DetectorConfig("n", backbone, p2=p2, p6=p6, num_classes=nc, **TINY))


def expected_anchors(h: int, w: int, strides: list[int]) -> int:
    return sum((h // s) * (w // s) for s in strides)


@pytest.mark.parametrize("backbone", sorted(BACKBONES))
@pytest.mark.parametrize("p2,p6,strides", [(True, False, [4, 8, 16, 32]), (False, False, [8, 16, 32]),
                                           (True, True, [4, 8, 16, 32, 64]), (False, True, [8, 16, 32, 64])])
def test_levels_shapes_and_anchors(backbone, p2, p6, strides):
    model = tiny(backbone, p2, p6, nc=3)
    assert model.strides == strides
    h, w = 64, 128
    out = model(torch.rand(2, 3, h, w))
    a = expected_anchors(h, w, strides)
    assert isinstance(out, HeadOutput)
    assert out.box.shape == (2, 4 * REG_MAX, a)
    assert out.cls.shape == (2, 3, a)
    assert out.kpt.shape == (2, NUM_KEYPOINTS * 3, a)
    assert out.anchors.shape == (a, 2) and out.strides.shape == (a,)
    # finest level first, row-major: the first anchor is the centre of the first finest cell
    s0 = strides[0]
    assert out.anchors[0].tolist() == [s0 / 2, s0 / 2]
    assert out.anchors[1].tolist() == [1.5 * s0, s0 / 2]
    counts = [int((out.strides == s).sum()) for s in strides]
    assert counts == [(h // s) * (w // s) for s in strides]
    assert torch.all(out.strides[1:] >= out.strides[:-1])


def test_backbone_features_at_every_stride():
    for name in BACKBONES:
        bb = build_backbone(name, 0.0625, 0.33, 64, p6=True)
        feats = bb(torch.rand(1, 3, 128, 128))
        assert sorted(feats) == [4, 8, 16, 32, 64]
        for s, f in feats.items():
            assert f.shape == (1, bb.channels[s], 128 // s, 128 // s)


@pytest.mark.parametrize("backbone", sorted(BACKBONES))
@pytest.mark.parametrize("scale", SCALE_NAMES)
def test_every_scale_builds(backbone, scale):
    model = KeypointDetector(DetectorConfig(scale, backbone, num_classes=1)).eval()
    with torch.no_grad():
        out = model(torch.rand(1, 3, 64, 64))
    assert out.box.shape[-1] == expected_anchors(64, 64, [4, 8, 16, 32])
    assert count_parameters(model) > 1e6


def test_scales_grow():
    for backbone in BACKBONES:
        sizes = [count_parameters(KeypointDetector(DetectorConfig(s, backbone, num_classes=1))) for s in "nsm"]
        assert sizes[0] < sizes[1] < sizes[2]


def test_decode_shape_and_ranges():
    model = tiny(nc=5).eval()
    with torch.no_grad():
        y = model.infer(torch.rand(2, 3, 64, 64))
    a = expected_anchors(64, 64, model.strides)
    assert y.shape == (2, 4 + 5 + NUM_KEYPOINTS * 3, a)
    boxes, scores, kpt = y[:, :4], y[:, 4:9], y[:, 9:].view(2, NUM_KEYPOINTS, 3, a)
    assert torch.all(boxes[:, 2] >= boxes[:, 0]) and torch.all(boxes[:, 3] >= boxes[:, 1])
    assert torch.all((scores > 0) & (scores < 1))
    assert torch.all((kpt[:, :, 2] > 0) & (kpt[:, :, 2] < 1))


def test_head_bias_init():
    model = tiny(nc=4)
    for box, cls, s in zip(model.head.box, model.head.cls, model.strides):
        assert torch.all(box[-1].bias == 1.0)
        assert torch.allclose(cls[-1].bias, torch.full((4,), float(np.log(5 / 4 / (640 / s) ** 2))))


def test_config_round_trip():
    cfg = DetectorConfig("s", "c2f", p2=False, p6=True, num_classes=7, width=0.5)
    data = cfg.to_dict()
    assert all(isinstance(v, (str, int, float, bool, type(None))) for v in data.values())
    assert DetectorConfig.from_dict(data) == cfg
    model = KeypointDetector(DetectorConfig.from_dict(tiny(p2=False, p6=True).cfg.to_dict()))
    assert model.strides == [8, 16, 32, 64]


def test_config_errors():
    with pytest.raises(ValueError, match="c2f.*c3k2"):
        DetectorConfig(backbone="resnet")
    with pytest.raises(ValueError, match="c2f.*c3k2"):
        build_backbone("resnet", 0.25, 0.33, 1024)
    with pytest.raises(ValueError, match="scale"):
        DetectorConfig(scale="q")
    with pytest.raises(ValueError, match="num_classes"):
        DetectorConfig(num_classes=0)
    with pytest.raises(ValueError, match="unknown fields"):
        DetectorConfig.from_dict({"scale": "n", "colour": "red"})
    with pytest.raises(ValueError, match="multiple of the largest stride"):
        tiny()(torch.rand(1, 3, 48, 64))
    with pytest.raises(ValueError, match="kpt_mode.*anchor, box"):
        DetectorConfig(kpt_mode="centre")


def test_box_mode_model_puts_fresh_corners_at_its_box_centres():
    """A 'box'-mode checkpoint's config says so, and its inference tensor decodes the corners in
    units of each anchor's own box: a fresh head (raw outputs near 0) predicts them near the centre."""
    model = KeypointDetector(DetectorConfig.from_dict({**tiny().cfg.to_dict(), "kpt_mode": "box"})).eval()
    with torch.no_grad():
        torch.nn.init.zeros_(model.head.kpt[0][-1].weight)
        torch.nn.init.zeros_(model.head.kpt[0][-1].bias)
        y = model.infer(torch.rand(1, 3, 64, 64))
    nc = model.cfg.num_classes
    first = y[0, :, 0]  # an anchor of the first level, whose kpt branch now outputs exactly 0
    centre = (first[:2] + first[2:4]) / 2
    corners = first[4 + nc:].view(8, 3)[:, :2]
    assert torch.allclose(corners, centre.expand(8, 2), atol=1e-5)


def test_gradient_reaches_every_parameter():
    model = tiny(p6=True).train()
    out = model(torch.rand(2, 3, 256, 256))  # P6 map 4 x 4: attention has more than one cell
    g = torch.Generator().manual_seed(1)
    loss = sum((t * torch.randn(t.shape, generator=g)).sum() for t in (out.box, out.cls, out.kpt))
    loss.backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None or not torch.any(p.grad != 0)]
    assert missing == []


def test_train_and_eval_modes():
    model = tiny()
    x = torch.rand(2, 3, 64, 64)
    out_train = model.train()(x)
    model.eval()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with torch.no_grad():
        a, b = model(x), model(x)
    # same layout in both modes; eval is deterministic and leaves the batch-norm statistics alone
    assert out_train.box.shape == a.box.shape and torch.equal(out_train.anchors, a.anchors)
    assert torch.equal(a.box, b.box) and torch.equal(a.kpt, b.kpt)
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    # eval output of one image does not depend on the rest of the batch (running statistics)
    with torch.no_grad():
        single = model(x[:1])
    assert torch.allclose(single.cls, a.cls[:1], atol=1e-5)
    # folding the batch-norms changes nothing but speed
    with torch.no_grad():
        ref = model.infer(x)
        fused = model.fuse().infer(x)
    assert torch.allclose(ref, fused, atol=1e-4, rtol=1e-4)


def test_fuse_refuses_training_mode():
    with pytest.raises(RuntimeError, match="eval"):
        tiny().train().fuse()


def test_gflops_counts_two_flops_per_mac():
    conv = nn.Conv2d(3, 8, 3, padding=1, bias=False)
    assert gflops(conv, imgsz=64) == pytest.approx(2 * 3 * 8 * 9 * 64 * 64 / 1e9)


def test_n_with_p2_stays_cheap():
    """The design budget that keeps n+P2 within reach of YOLO11n-pose on a CPU (docs/detector-model.md)."""
    for backbone in BACKBONES:
        model = KeypointDetector(DetectorConfig("n", backbone, p2=True, num_classes=1))
        assert gflops(model, 640) < 8.0


@pytest.mark.skipif(importlib.util.find_spec("onnx") is None,
                    reason="torch.onnx.export (TorchScript exporter, dynamo=False) needs the 'onnx' package, "
                           "which is not installed; the dynamo exporter needs 'onnxscript' as well")
def test_onnx_export_matches_pytorch(tmp_path):
    import onnxruntime as ort

    model = tiny(nc=2).eval()
    x = torch.rand(1, 3, 64, 96)
    path = tmp_path / "tiny.onnx"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.onnx.export(InferenceWrapper(model), (x,), str(path), opset_version=18, dynamo=False,
                          input_names=["images"], output_names=["output"])
    # the graph holds no Python-side decision frozen at the traced size
    assert not [w for w in caught if issubclass(w.category, torch.jit.TracerWarning)], [str(w.message) for w in caught]
    from omnigen.detector.prediction.export_onnx import export

    with pytest.raises(ValueError, match="--imgsz 72: .* multiple of the largest stride 32"):
        export(model, tmp_path / "bad.onnx", 72)  # the size the model no longer checks while traced
    assert not (tmp_path / "bad.onnx").exists()
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"images": x.numpy()})[0]
    with torch.no_grad():
        want = model.infer(x).numpy()
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, atol=1e-4, rtol=1e-4)
