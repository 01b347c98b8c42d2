"""Issue 48: a Cycles frame is the same bytes whatever the process rendered before it.

A Renderer keeps its Blender scene from frame to frame (objects, meshes and materials reused), so
a run's frame must come out exactly as a fresh Renderer rendering only that frame makes it: image,
depth, instance mask and record. Night frames, so the street lamps are lit in every frame: with
the scene rebuilt per frame Cycles' persistent session kept the lamps in another order after the
first frame, and the image differed.
"""

from __future__ import annotations

from pathlib import Path

import pytest

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
pytest.importorskip("bpy", reason="bpy not installed")

W, H, SEED = 64, 48, 3
LAST = 2


def _render(out: Path, start: int, frames: int) -> Path:
    from omnigen.rigs.render import RenderJob, Renderer
    from omnigen.scenes.generate import FrameOverrides

    # labels by Cycles itself: no headless GL needed, and its label passes are part of the history
    job = RenderJob(rig="pole", frames=frames, start=start, out=out, seed=SEED, scene="tiny", width=W, height=H,
                    backend="cycles", quality="preview", labels="cycles", durable=False,
                    overrides=FrameOverrides(time_of_day="night"))
    r = Renderer(job)
    try:
        for i in range(start, start + frames):
            r.render_frame(i)
    finally:
        r.close()
    return out


def _files(root: Path, frame_id: str) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for sub in ("images", "depth", "instance", "records")
            for p in sorted((root / sub).glob(f"{frame_id}*"))}


def test_a_cycles_frame_after_others_equals_the_frame_alone(tmp_path):
    from omnigen.rigs.render import frame_id_for

    seq = _render(tmp_path / "seq", 0, LAST + 1)
    alone = _render(tmp_path / "alone", LAST, 1)
    fid = frame_id_for("pole", SEED, LAST)
    want = _files(alone, fid)
    assert len(want) == 4
    assert _files(seq, fid) == want
