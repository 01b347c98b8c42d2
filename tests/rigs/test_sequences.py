"""Issue 46: temporal capture with one rig (`omnigen render --sequence-length L --fps F`).

A sequence is L consecutive instants of one moving world (scenes/world.py) seen by a camera drawn
at instant 0 and held. Checks: the record fields (sequence, timestamp, camera_to_world, per object
track_id and velocity), that tracks keep their ids and move plausibly in the world, masks inside
the projected cuboids at every instant, byte-identical reruns, shards of whole sequences and a
resume in mid-sequence equal to an uninterrupted run, the flags' one-line refusals, and that
independent frames (L = 1) carry camera_to_world and track_id but no sequence fields.
"""

from __future__ import annotations

import json
import shutil
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from omnigen.cli import main
from omnigen.record import FrameRecord
from omnigen.scenes.generate import SceneGenerator
from rendered_dataset import masks_inside_cuboids, read_records, same_files

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
pytest.importorskip("pyrender", reason="pyrender not installed")
pytest.importorskip("OpenGL", reason="PyOpenGL not installed")

W, H = 96, 64
SEED, FPS, L, FRAMES = 7, 10.0, 3, 6


def _render(out: Path, *extra: str, frames: int = FRAMES, length: int = L) -> int:
    return main(["render", "--rig", "drone", "--frames", str(frames), "--sequence-length", str(length),
                 "--fps", str(FPS), "--seed", str(SEED), "--width", str(W), "--height", str(H),
                 "--backend", "raster", "--scene", "tiny", "--out", str(out), *extra])


@pytest.fixture(scope="module")
def seq(tmp_path_factory, headless_gl) -> Path:
    out = tmp_path_factory.mktemp("seq") / "d"
    assert _render(out) == 0
    return out


def _world_centre(rec: FrameRecord, o) -> np.ndarray:
    return (rec.camera_to_world @ np.r_[o.box.center, 1.0])[:3]


def test_records_carry_sequence_fields(seq):
    recs = read_records(seq)
    assert [r.frame_id for r in recs] == [f"synthetic-drone-s{SEED}-{i:06d}" for i in range(FRAMES)]
    assert [r.sequence for r in recs] == [f"synthetic-tiny-s{SEED}-q{q:06d}" for q in (0, 0, 0, 1, 1, 1)]
    assert [r.timestamp for r in recs] == pytest.approx([0.0, 0.1, 0.2] * 2)
    first = {r.sequence: r for r in reversed(recs)}
    for r in recs:
        assert r.camera_to_world.shape == (4, 4) and r.objects
        assert np.array_equal(r.camera_to_world, first[r.sequence].camera_to_world)  # held for the sequence
        for o in r.objects:
            assert o.track_id == o.instance_id and o.velocity is not None
    assert not np.array_equal(recs[0].camera_to_world, recs[3].camera_to_world)  # drawn per sequence
    manifest = json.loads((seq / "manifest.json").read_text())["render"]
    assert (manifest["sequence_length"], manifest["fps"]) == (L, FPS)


def test_tracks_keep_ids_move_and_agree_with_velocity(seq):
    """World centres (camera_to_world @ box centre) of one track across a sequence's instants:
    something moves, nothing faster than 40 m/s, and the record's velocity matches the finite
    difference within 1 m/s for moving tracks (the motion is smooth over 0.1 s)."""
    recs = read_records(seq)
    by_seq: dict[str, dict[int, list]] = defaultdict(lambda: defaultdict(list))
    for r in recs:
        for o in r.objects:
            by_seq[r.sequence][o.track_id].append((r.timestamp, _world_centre(r, o), o.velocity, o.category))
    moved = checked = 0
    for tracks in by_seq.values():
        for tid, seen in tracks.items():
            assert len({c for *_, c in seen}) == 1, tid  # one physical agent keeps its id and class
            for (t0, p0, v0, _), (t1, p1, v1, _) in zip(seen, seen[1:]):
                step = np.linalg.norm(p1[:2] - p0[:2])
                assert step / (t1 - t0) <= 40.0, (tid, step)
                if step > 0.05:
                    moved += 1
                    fd = (p1 - p0) / (t1 - t0)
                    assert np.linalg.norm(fd[:2] - (v0[:2] + v1[:2]) / 2) <= 1.0, (tid, fd, v0, v1)
                    checked += 1
                else:
                    assert np.linalg.norm(v0) < 1.0 and np.linalg.norm(v1) < 1.0, (tid, v0, v1)
    assert moved >= 1 and checked >= 1


def test_masks_inside_projected_cuboids_every_instant(seq):
    """tests/rigs/test_render.py's rule, at every instant: the box a record gives projects over its mask."""
    assert masks_inside_cuboids(seq) >= FRAMES


def test_rerun_and_shards_equal_one_run(seq, tmp_path):
    assert _render(tmp_path / "again") == 0
    same_files(seq, tmp_path / "again")
    sharded = tmp_path / "sharded"
    assert _render(sharded, "--shard", "1/2") == 0
    # shard 1 of 2 renders sequence 0 whole: instants 0-2
    assert sorted(p.name[-11:-5] for p in (sharded / "records").iterdir()) == ["000000", "000001", "000002"]
    assert _render(sharded, "--shard", "2/2") == 0
    same_files(seq, sharded)


def test_resume_mid_sequence_identical(seq, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(seq, copy)
    for i in (1, 2, 4):  # instant 0 of each sequence is kept: the world and camera are rebuilt without it
        (copy / "records" / f"synthetic-drone-s{SEED}-{i:06d}.json").unlink()
    (copy / "manifest.json").unlink()
    assert _render(copy) == 0
    same_files(seq, copy)


@pytest.mark.parametrize("args, says", [
    (("--frames", "5", "--sequence-length", "3"), "--frames 5 and --start 0 must be multiples of --sequence-length 3"),
    (("--frames", "6", "--sequence-length", "3", "--start", "2"), "--frames 6 and --start 2 must be multiples"),
])
def test_partial_sequences_refused_in_one_line(tmp_path, capsys, args, says):
    assert main(["render", "--rig", "drone", "--out", str(tmp_path / "x"), "--scene", "tiny", "--backend", "raster",
                 *args]) == 1
    err = capsys.readouterr().err.strip()
    assert says in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("flag, value", [("--sequence-length", "0"), ("--fps", "0"), ("--fps", "nan")])
def test_bad_sequence_flags_refused_when_parsed(tmp_path, capsys, flag, value):
    with pytest.raises(SystemExit):
        main(["render", "--rig", "drone", "--frames", "3", "--out", str(tmp_path / "x"), "--scene", "tiny", flag, value])
    assert f"argument {flag}" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_changed_sequence_flags_refused_on_resume(seq, tmp_path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(seq, copy)
    assert main(["render", "--rig", "drone", "--frames", "6", "--sequence-length", "3", "--fps", "5",
                 "--seed", str(SEED), "--width", str(W), "--height", str(H), "--backend", "raster",
                 "--scene", "tiny", "--out", str(copy)]) == 1
    assert "--fps: 10.0 there, 5.0 now" in capsys.readouterr().err


def test_independent_frames_fill_pose_and_track_only(tmp_path, headless_gl):
    """L = 1: no sequence, timestamp or velocity; camera_to_world maps each box centre back onto
    its agent's world centre (so it inverts the camera's R and t); track_id = instance id; and
    `.render-args.json` names no sequence flag (folders rendered before sequences resume)."""
    out = tmp_path / "one"
    assert _render(out, frames=2, length=1) == 0
    args = json.loads((out / ".render-args.json").read_text())
    assert "sequence_length" not in args and "fps" not in args
    gen = SceneGenerator("tiny", SEED)
    for i, rec in enumerate(read_records(out)):
        assert rec.sequence is None and rec.timestamp is None
        agents = {a.instance_id: a for a in gen.frame(SEED, i).agents}
        for o in rec.objects:
            assert o.track_id == o.instance_id and o.velocity is None
            assert np.allclose(_world_centre(rec, o), agents[o.instance_id].center, atol=1e-6)


def test_ray_refuses_sequences_before_writing(tmp_path, capsys):
    assert main(["render", "--rig", "drone", "--frames", "3", "--sequence-length", "3", "--out", str(tmp_path / "x"),
                 "--scene", "tiny", "--backend", "raster", "--executor", "ray"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--executor ray renders independent frames only" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_sequences_draw_nothing_ahead(tmp_path):
    """A sequence's instants come from its World here; FramesAhead stays for independent frames."""
    from omnigen.rigs.render import AHEAD_MIN_FRAMES, Renderer, RenderJob

    n = 3 * AHEAD_MIN_FRAMES
    job = RenderJob(rig="drone", frames=n, out=tmp_path / "a", scene="tiny", backend="raster", sequence_length=3)
    r = Renderer(job)
    try:
        assert not r.draw_ahead(n)
    finally:
        r.close()


def test_rain_is_drawn_anew_each_instant():
    """The precipitation overlay's stream is the instant's (scenes/seeding.py instant_extra_rng):
    instant 0 keeps the legacy frame's streaks, later instants get their own."""
    from omnigen.scenes.generate import FrameOverrides
    from omnigen.scenes.raster_backend import _precipitation
    from omnigen.scenes.world import World

    gen = SceneGenerator("tiny", SEED)
    world = World.build(gen.city, gen.preset, SEED, 2, FrameOverrides(weather="rain", precipitation=1.0))
    grey = np.full((H, W, 3), 128, np.uint8)
    legacy = _precipitation(grey, gen.frame(SEED, 2, FrameOverrides(weather="rain", precipitation=1.0)))
    first, second = (_precipitation(grey, world.scene_at(k, FPS)) for k in (0, 1))
    assert np.array_equal(first, legacy) and not np.array_equal(first, second)
