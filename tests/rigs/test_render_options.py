"""Weather and time of day fixed on the command line, and --save-blend."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from omnigen.cli import main


def _needs_bpy() -> None:
    """Cycles needs Blender's Python module (labels fall back to Cycles' own passes without EGL)."""
    pytest.importorskip("bpy", reason="Blender's bpy not installed")


def _records(out: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((out / "records").glob("*.json"))]


@pytest.mark.usefixtures("headless_gl")
def test_fixed_weather_and_time_of_day_reach_every_frame(tmp_path):
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


def test_save_blend_writes_a_blend_file(tmp_path, monkeypatch):
    _needs_bpy()
    import omnigen.scenes.blender_backend as bb

    calls = []
    real = bb.develop_frame
    monkeypatch.setattr(bb, "develop_frame", lambda *a, **k: calls.append(1) or real(*a, **k))
    blend = tmp_path / "scene.blend"
    assert main(["render", "--rig", "pole", "--frames", "1", "--scene", "tiny", "--quality", "preview",
                 "--width", "48", "--height", "32", "--save-blend", str(blend), "--out", str(tmp_path / "ds")]) == 0
    head = blend.read_bytes()[:7]
    # Blender writes either a plain .blend ("BLENDER") or a zstd-compressed one.
    assert head == b"BLENDER" or head[:4] == b"\x28\xb5\x2f\xfd"
    assert blend.stat().st_size > 10_000
    assert len(calls) == 1  # the frame's image is developed once, for the writer and the .blend's exposure alike


# --- issue 27: a render folder records its arguments ------------------------------------------


def _raster(out: Path, *extra: str, frames: int = 2, width: int = 64) -> int:
    return main(["render", "--rig", "pole", "--frames", str(frames), "--scene", "tiny", "--backend", "raster",
                 "--width", str(width), "--height", "48", "--seed", "3", "--out", str(out), *extra])


def _widths(out: Path) -> list[int]:
    return [r["width"] for r in _records(out)]


@pytest.mark.usefixtures("headless_gl")
def test_a_resumed_render_with_other_arguments_is_refused(tmp_path, capsys):
    """Issue 27: killed part-way and rerun with another --width, a render added frames of the new
    size to the old ones, the manifest claimed the new size and validate said valid."""
    from omnigen.rigs.render import RenderJob, Renderer

    out = tmp_path / "ds"
    assert _raster(out, frames=3) == 0
    args = json.loads((out / ".render-args.json").read_text())
    assert (args["width"], args["height"], args["rig"], args["seed"], args["backend"]) == (64, 48, "pole", 3, "raster")
    # a kill after two frames: the third record and the manifest are not there
    (out / "manifest.json").unlink()
    sorted((out / "records").glob("*.json"))[-1].unlink()
    capsys.readouterr()
    assert _raster(out, frames=3, width=80) == 1
    err = capsys.readouterr().err
    assert "--width: 64 there, 80 now" in err and "--fresh" in err
    assert _widths(out) == [64, 64] and not (out / "manifest.json").exists()
    assert _raster(out, "--weather", "fog", frames=3) == 1  # any frame-deciding argument
    assert "--weather: unset there, fog now" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--height: 48 there, 40 now"):  # the API refuses as the command does
        Renderer(RenderJob(rig="pole", frames=3, out=out, seed=3, scene="tiny", width=64, height=40, backend="raster"))
    # the same arguments resume; --frames and --start are no such argument
    assert _raster(out, frames=3) == 0 and _widths(out) == [64, 64, 64]
    assert main(["validate", str(out)]) == 0
    # --fresh starts over with the new ones
    assert _raster(out, "--fresh", frames=2, width=80) == 0
    assert _widths(out) == [80, 80] and json.loads((out / ".render-args.json").read_text())["width"] == 80
    assert main(["validate", str(out)]) == 0
    assert _raster(out, "--fresh", "--shard", "1/2", frames=2) == 2


def test_fresh_touches_no_folder_that_is_not_a_render(tmp_path, capsys):
    theirs = tmp_path / "theirs"
    (theirs / "records").mkdir(parents=True)
    (theirs / "records" / "kitti-000001.json").write_text("{}")
    (theirs / "notes.txt").write_text("mine")
    assert main(["render", "--rig", "pole", "--frames", "1", "--scene", "tiny", "--backend", "raster",
                 "--fresh", "--out", str(theirs)]) == 1
    assert "no render folder" in capsys.readouterr().err
    assert sorted(p.name for p in theirs.rglob("*")) == ["kitti-000001.json", "notes.txt", "records"]


@pytest.mark.usefixtures("headless_gl")
def test_validate_catches_frames_that_disagree_with_the_folders_arguments(tmp_path, capsys):
    """A folder mixed before the arguments were recorded: its manifest claims one size, frames hold another."""
    out = tmp_path / "ds"
    assert _raster(out) == 0
    (out / ".render-args.json").unlink()
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["render"]["width"] = 80
    (out / "manifest.json").write_text(json.dumps(manifest))
    capsys.readouterr()
    assert main(["validate", str(out)]) == 1
    wanted = ": width: 64 but the folder was rendered with 80"
    lines = [line for line in capsys.readouterr().out.splitlines() if wanted in line]
    assert len(lines) == 2
    # and a rerun there is refused by what the manifest says
    assert _raster(out, width=64) == 1
    assert "--width: 80 there, 64 now" in capsys.readouterr().err
