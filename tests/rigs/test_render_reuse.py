"""Reuse between frames changes no byte (issue 48): a Renderer keeps the city, the GL scene and
their caches from frame to frame, and `omnigen render` draws each next frame's scene in a second
process; a frame must come out exactly as a fresh Renderer that renders only that frame makes it
(image, depth, instance mask and record), for every rig, so a run's frames equal a resumed run's,
a shard's and a Ray actor's whatever they rendered before. (Frame 0 of a sequence is itself
rendered by a fresh Renderer; the last frame is compared.)
"""

from __future__ import annotations

from pathlib import Path

import pytest

import omnigen.rigs.render as render
from omnigen.rigs.render import RenderJob, Renderer
from omnigen.scenes.generate import SceneGenerator

pytestmark = pytest.mark.usefixtures("headless_gl")

RIGS = sorted(p.stem for p in (Path(__file__).resolve().parents[2] / "rigs" / "presets").glob("*.toml"))
FRAMES = (0, 1, 2)


def _job(out: Path, rig: str, scene: str, start: int, frames: int) -> RenderJob:
    return RenderJob(rig=rig, frames=frames, start=start, out=out, seed=4, scene=scene, width=64, height=48,
                     backend="raster", durable=False)


def _files(root: Path, rel: str) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for sub in ("images", "depth", "instance", "records")
            for p in sorted((root / sub).glob(f"*{rel}*"))}


def _same_as_alone(tmp: Path, seq: Path, rig: str, scene: str) -> None:
    """The last frame in `seq`, rendered after a first frame (which builds everything) and a
    second (the first to reuse it), equals a fresh Renderer's of that frame alone."""
    i = FRAMES[-1]
    alone = Renderer(_job(tmp / "alone", rig, scene, i, 1))
    alone.render_frame(i)
    alone.close()
    fid = alone.frame_id(i)
    want = _files(tmp / "alone", fid)
    assert len(want) == 4
    assert _files(seq, fid) == want, f"{rig} {scene} frame {i}"


def test_the_rigs_are_found():
    assert {"drone", "ego", "pole"} <= set(RIGS)


@pytest.mark.parametrize("scene", ["tiny", "intersection"])
@pytest.mark.parametrize("rig", RIGS)
def test_a_frame_after_others_equals_the_frame_alone(tmp_path, rig, scene):
    seq = Renderer(_job(tmp_path / "seq", rig, scene, 0, len(FRAMES)))
    seq.write_behind = True  # as `omnigen render` runs: shading and writing overlap the next frame
    for i in FRAMES:
        seq.render_frame(i)
    seq.close()
    _same_as_alone(tmp_path, tmp_path / "seq", rig, scene)


def test_frames_drawn_ahead_equal_the_frame_alone(tmp_path, monkeypatch):
    monkeypatch.setattr(render, "AHEAD_MIN_FRAMES", 1)  # a run this short draws ahead too,
    monkeypatch.setattr(render.os, "sched_getaffinity", lambda pid: {0, 1})  # on any machine
    drawn_here = []
    real = SceneGenerator.frame
    monkeypatch.setattr(SceneGenerator, "frame", lambda self, *a: drawn_here.append(a[1]) or real(self, *a))
    Renderer(_job(tmp_path / "seq", "drone", "tiny", 0, len(FRAMES))).run(show_progress=False)
    assert drawn_here == [0]  # frames 1 and 2 came from the worker
    monkeypatch.setattr(SceneGenerator, "frame", real)
    _same_as_alone(tmp_path, tmp_path / "seq", "drone", "tiny")


def test_frames_are_drawn_ahead_only_where_it_pays(tmp_path, monkeypatch):
    from dataclasses import replace

    job = _job(tmp_path / "a", "pole", "tiny", 0, 3)
    monkeypatch.setattr(render.os, "sched_getaffinity", lambda pid: {0})
    assert not Renderer(job).draw_ahead(10 * render.AHEAD_MIN_FRAMES)  # one core: nothing to overlap with
    monkeypatch.setattr(render.os, "sched_getaffinity", lambda pid: {0, 1})
    assert not Renderer(job).draw_ahead(render.AHEAD_MIN_FRAMES - 1)  # too short a run to repay the worker
    assert not Renderer(replace(job, ahead=False)).draw_ahead(render.AHEAD_MIN_FRAMES)  # the job says no
    r = Renderer(job)
    assert r.draw_ahead(render.AHEAD_MIN_FRAMES) and r.ahead is not None
    r.close()
    assert r.ahead is None


def test_a_camera_drawn_ahead_and_redrawn_equals_the_frame_alone(tmp_path, monkeypatch):
    """The worker draws each frame's first camera with its scene (render.first_camera) and hands
    back the rig's stream as the draw left it: a redraw (fewer objects annotated than the rig asks)
    goes on with it exactly as a frame drawn here does."""
    from dataclasses import replace

    monkeypatch.setattr(render, "AHEAD_MIN_FRAMES", 1)
    monkeypatch.setattr(render.os, "sched_getaffinity", lambda pid: {0, 1})
    real, first_seen = render.annotate, set()

    def first_look_finds_nothing(scene, cam, *rest):  # each frame's first camera is redrawn once
        ann = real(scene, cam, *rest)
        if (scene.dataset_seed, scene.frame_index) in first_seen:
            return ann
        first_seen.add((scene.dataset_seed, scene.frame_index))
        return replace(ann, objects=[])
    monkeypatch.setattr(render, "annotate", first_look_finds_nothing)
    seq = Renderer(_job(tmp_path / "seq", "drone", "tiny", 0, len(FRAMES)))
    seq.run(show_progress=False)
    assert seq.summary.redraws == len(FRAMES)
    first_seen.clear()
    _same_as_alone(tmp_path, tmp_path / "seq", "drone", "tiny")
