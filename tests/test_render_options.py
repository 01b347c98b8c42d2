"""Weather and time of day fixed on the command line, and --save-blend."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from omnigen.cli import main


def _needs_egl() -> None:
    """The raster backend needs pyrender, PyOpenGL and a headless EGL context."""
    pytest.importorskip("pyrender", reason="pyrender not installed")
    pytest.importorskip("OpenGL", reason="PyOpenGL not installed")
    from scenes.gl_raster import GLRaster

    try:
        GLRaster().close()
    except Exception as exc:
        pytest.skip(f"headless EGL rendering unavailable: {exc}")


def _needs_bpy() -> None:
    """Cycles needs Blender's Python module (labels fall back to Cycles' own passes without EGL)."""
    pytest.importorskip("bpy", reason="Blender's bpy not installed")


def _records(out: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((out / "records").glob("*.json"))]


def test_fixed_weather_and_time_of_day_reach_every_frame(tmp_path):
    _needs_egl()
    out = tmp_path / "ds"
    assert main(["render", "--rig", "pole", "--frames", "2", "--scene", "tiny", "--backend", "raster",
                 "--width", "64", "--height", "48", "--weather", "snow", "--time-of-day", "dusk",
                 "--out", str(out)]) == 0
    recs = _records(out)
    assert len(recs) == 2
    assert {r["synthetic"]["weather"]["kind"] for r in recs} == {"snow"}
    assert {r["synthetic"]["lighting"]["time_of_day"] for r in recs} == {"dusk"}


def test_bad_options_are_refused(tmp_path, capsys):
    assert main(["render", "--rig", "pole", "--frames", "1", "--weather", "hail", "--out", str(tmp_path / "x")]) == 2
    assert "--weather is one of" in capsys.readouterr().err
    assert main(["render", "--rig", "pole", "--frames", "1", "--backend", "raster", "--save-blend",
                 str(tmp_path / "a.blend"), "--out", str(tmp_path / "y")]) == 2
    assert "--save-blend needs --backend cycles" in capsys.readouterr().err


def test_save_blend_writes_a_blend_file(tmp_path):
    _needs_bpy()
    blend = tmp_path / "scene.blend"
    assert main(["render", "--rig", "pole", "--frames", "1", "--scene", "tiny", "--quality", "preview",
                 "--width", "48", "--height", "32", "--save-blend", str(blend), "--out", str(tmp_path / "ds")]) == 0
    head = blend.read_bytes()[:7]
    # Blender writes either a plain .blend ("BLENDER") or a zstd-compressed one.
    assert head == b"BLENDER" or head[:4] == b"\x28\xb5\x2f\xfd"
    assert blend.stat().st_size > 10_000
