"""Write-behind (issue 26's frame rate): `omnigen render` writes each frame's files on a thread
while the next frame is drawn. The files must be the same bytes as writing in line, a frame's
record must come after its images, and a failed write must not pass unnoticed."""

from __future__ import annotations

from pathlib import Path

import pytest

import omnigen.rigs.render as render
from omnigen.rigs.render import RenderJob, Renderer

pytestmark = pytest.mark.usefixtures("headless_gl")


def _job(out: Path, frames: int = 3) -> RenderJob:
    return RenderJob(rig="pole", frames=frames, out=out, seed=2, scene="tiny", width=64, height=48, backend="raster",
                     quality="preview", durable=False)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for sub in ("images", "depth", "instance", "records")
            for p in sorted((root / sub).glob("*"))}


def test_write_behind_writes_the_same_bytes_as_writing_in_line(tmp_path):
    Renderer(_job(tmp_path / "behind")).run(show_progress=False)  # run() writes behind
    inline = Renderer(_job(tmp_path / "inline"))
    assert not inline.write_behind
    for i in range(3):
        inline.render_frame(i)
        # in line, the frame is on disk when render_frame returns
        assert (tmp_path / "inline" / "records" / f"{inline.frame_id(i)}.json").exists()
    inline.close()
    behind, line = _files(tmp_path / "behind"), _files(tmp_path / "inline")
    assert len(line) == 4 * 3 and behind == line


def test_a_frames_record_is_written_after_its_files(tmp_path, monkeypatch):
    order = []
    real_bytes, real_exr = render.atomic_write_bytes, render.write_depth_exr
    monkeypatch.setattr(render, "atomic_write_bytes", lambda path, *a, **k: order.append(Path(path).parent.name) or real_bytes(path, *a, **k))
    monkeypatch.setattr(render, "write_depth_exr", lambda path, *a: order.append("depth") or real_exr(path, *a))
    r = Renderer(_job(tmp_path / "ds", frames=2))
    real_write = r.writer.write
    monkeypatch.setattr(r.writer, "write", lambda rec: order.append("records") or real_write(rec))
    r.run(show_progress=False)
    assert order == ["images", "depth", "instance", "records"] * 2


def test_a_failed_write_is_raised(tmp_path, monkeypatch):
    r = Renderer(_job(tmp_path / "ds", frames=2))
    r.write_behind = True

    def broken(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(render, "write_depth_exr", broken)
    r.render_frame(0)  # returns: its image is read back and its files written later
    r.render_frame(1)
    assert not list((tmp_path / "ds" / "records").glob("*.json"))
    with pytest.raises(OSError, match="disk full"):
        r.flush()  # at the latest when everything rendered is flushed (run() does in close())
    r.close()
    assert not list((tmp_path / "ds" / "records").glob("*.json"))  # no record without its files


def test_a_camera_annotation_rejects_is_not_shaded(tmp_path, monkeypatch):
    """With the colour pass deferred, only the kept camera of each frame is shaded: here
    annotation finds too few objects for every frame's first camera (as when buildings hide what
    the geometric estimate counted), so each frame is drawn twice and shaded once."""
    import dataclasses

    from omnigen.scenes import gl_raster

    calls, seen = [], set()
    real_draw, real_annotate = gl_raster.GLRaster.color_draw, render.annotate

    def first_camera_finds_nothing(scene, *a, **k):
        ann = real_annotate(scene, *a, **k)
        if scene.frame_index in seen:
            return ann
        seen.add(scene.frame_index)
        return dataclasses.replace(ann, objects=[])

    monkeypatch.setattr(gl_raster.GLRaster, "color_draw", lambda self, *a, **k: calls.append(1) or real_draw(self, *a, **k))
    monkeypatch.setattr(render, "annotate", first_camera_finds_nothing)
    summary = Renderer(_job(tmp_path / "ds", frames=2)).run(show_progress=False)
    assert summary.redraws == 2  # one camera a frame rejected
    assert len(calls) == 2  # one colour pass a frame: the kept camera's
    assert len(list((tmp_path / "ds" / "images").glob("*.png"))) == 2
