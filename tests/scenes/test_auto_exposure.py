"""The raster preview's camera: sRGB output encoding, its tone curve and the automatic exposure (gl_raster.auto_exposure).
Pure numpy on small arrays whose answer is known; no GL needed."""

from __future__ import annotations

import numpy as np
import pytest

gl_raster = pytest.importorskip("omnigen.scenes.gl_raster", reason="PyOpenGL not installed")


def _metered_mean(rgb: np.ndarray) -> float:
    lin = gl_raster.decode(rgb / 255.0)
    return float((lin @ np.array([0.2126, 0.7152, 0.0722])).mean())


def test_srgb_encoding_round_trips_and_has_the_linear_toe():
    x = np.linspace(0.0, 1.0, 101)
    assert np.allclose(gl_raster.srgb_decode(gl_raster.srgb_encode(x)), x, atol=1e-9)
    assert gl_raster.srgb_encode(np.array([0.002]))[0] == pytest.approx(12.92 * 0.002)
    assert gl_raster.srgb_encode(np.array([0.18]))[0] == pytest.approx(0.4614, abs=1e-3)  # 18% grey: code 118


def test_the_tone_curve_is_an_s_that_keeps_black_mid_grey_and_white_and_inverts():
    v = np.linspace(0.0, 1.0, 1001)
    t = gl_raster.tone(v)
    assert gl_raster.tone(np.array([0.0, 0.5, 1.0])) == pytest.approx([0.0, 0.5, 1.0])
    assert (np.diff(t) > 0).all()  # monotone: no two code values swap
    slope = np.gradient(t, v)
    assert slope[500] == pytest.approx(1.0 + 0.5 * gl_raster.TONE_CONTRAST, rel=1e-3)  # steeper at mid-grey
    assert slope[0] < 1.0 and slope[-1] < 1.0  # flatter at the ends
    assert t[250] < v[250] and t[750] > v[750]  # darker shadows, brighter highlights
    assert np.allclose(gl_raster.untone(t), v, atol=1e-6)
    x = np.linspace(0.0, 1.0, 101)
    assert np.allclose(gl_raster.decode(gl_raster.encode(x)), x, atol=1e-6)


def test_a_dark_frame_is_opened_up_to_mid_grey():
    rgb = np.full((32, 32, 3), 60, dtype=np.uint8)
    rgb[:4, :4] = 255  # a saturated highlight stays saturated
    out = gl_raster.auto_exposure(rgb, max_gain=4.0)
    assert _metered_mean(out[::gl_raster.AE_STRIDE, ::gl_raster.AE_STRIDE]) == pytest.approx(gl_raster.AE_TARGET, abs=0.01)
    assert (out[:4, :4] == 255).all() and out[8, 8, 0] > 60


def test_the_gain_is_capped_and_order_is_kept():
    rgb = np.tile(np.arange(0, 40, dtype=np.uint8)[None, :, None], (8, 1, 3))  # a very dark ramp
    out = gl_raster.auto_exposure(rgb, max_gain=2.0)
    lin_in, lin_out = gl_raster.decode(rgb[0, 1:, 0] / 255.0), gl_raster.decode(out[0, 1:, 0] / 255.0)
    assert np.allclose(lin_out / lin_in, 2.0, rtol=0.15)  # capped at 2 (8-bit rounding aside)
    assert (np.diff(out[0, :, 0].astype(int)) >= 0).all()


def test_bright_frames_and_no_gain_are_left_alone():
    bright = np.full((16, 16, 3), 200, dtype=np.uint8)
    assert gl_raster.auto_exposure(bright, max_gain=4.0) is bright  # above the target: unchanged
    dark = np.full((16, 16, 3), 30, dtype=np.uint8)
    assert gl_raster.auto_exposure(dark, max_gain=1.0) is dark  # night: the gain is spent already
