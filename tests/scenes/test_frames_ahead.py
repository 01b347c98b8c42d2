"""Frames drawn ahead in a second process (issue 48) are the frames drawn here: the same agents,
weather and light (to the byte of their JSON), on this process's city object."""

from __future__ import annotations

import os
import signal

from omnigen.scenes.description import to_json
from omnigen.scenes.generate import FrameOverrides, FramesAhead, SceneGenerator


def test_a_frame_drawn_ahead_is_the_frame_drawn_here():
    gen = SceneGenerator("tiny", 6)
    ahead = FramesAhead(gen)
    fixed = FrameOverrides(weather="rain", time_of_day="dusk")
    try:
        ahead.ask(6, 3)
        ahead.ask(9, 1, fixed)  # another dataset seed over the same city, weather fixed
        for seed, index, overrides in ((6, 3, None), (9, 1, fixed)):
            got, want = ahead.frame(seed, index, overrides), gen.frame(seed, index, overrides)
            assert got.city is gen.city
            assert to_json(got) == to_json(want) and got == want
        assert not ahead._asked
        # a frame not asked for is drawn here
        assert to_json(ahead.frame(6, 4)) == to_json(gen.frame(6, 4))
        # a dead worker: the frame is drawn here, and frames are no longer asked of it
        for pid in list(ahead._pool._processes):
            os.kill(pid, signal.SIGKILL)
        ahead.ask(6, 5)
        assert to_json(ahead.frame(6, 5)) == to_json(gen.frame(6, 5))
        assert ahead._pool is None
        ahead.ask(6, 6)
        assert to_json(ahead.frame(6, 6)) == to_json(gen.frame(6, 6))
    finally:
        ahead.close()


def test_meshes_built_ahead_are_adopted_and_equal_a_build_here(monkeypatch):
    """With meshes=True the worker builds the frame's agent meshes and this process adopts them:
    agent_parts then builds nothing (no builder is reachable) and gives the very arrays a build
    here gives. Without it the worker's meshes are not sent (the raster builds only agents in view)."""
    from omnigen.scenes.assets import build

    monkeypatch.setattr(build, "_CACHE", type(build._CACHE)())
    gen = SceneGenerator("tiny", 6)
    ahead = FramesAhead(gen, meshes=True)
    try:
        ahead.ask(6, 2)
        scene = ahead.frame(6, 2)
    finally:
        ahead.close()
    assert len(build._CACHE) == len({build._agent_key(a.asset, a.dims) for a in scene.agents}) > 0
    with monkeypatch.context() as m:
        m.setattr(build, "AGENT_BUILDERS", {})
        adopted = [build.agent_parts(a.asset, a.dims) for a in scene.agents]
    build._CACHE.clear()
    for a, (parts, raw) in zip(scene.agents, adopted):
        here, raw_here = build.agent_parts(a.asset, a.dims)
        assert parts is not here and list(parts) == list(here) and raw.tobytes() == raw_here.tobytes()
        for role in parts:
            assert parts[role].vertices.tobytes() == here[role].vertices.tobytes()
            assert parts[role].faces.tobytes() == here[role].faces.tobytes()
    plain = FramesAhead(gen)
    try:
        build._CACHE.clear()
        plain.ask(6, 3)
        plain.frame(6, 3)
        assert not build._CACHE
    finally:
        plain.close()


def _made_in(scene):
    return os.getpid(), len(scene.agents), scene.frame_index


def test_what_then_makes_of_a_frame_comes_back_with_it():
    """FramesAhead(then=f) runs f on each frame asked for in the worker (another process) and
    frame_with hands back its result; a frame drawn here comes back with None (the caller makes it)."""
    gen = SceneGenerator("tiny", 6)
    ahead = FramesAhead(gen, then=_made_in)
    try:
        ahead.ask(6, 3)
        scene, made = ahead.frame_with(6, 3)
        assert made[0] != os.getpid() and made[1:] == (len(scene.agents), 3)
        assert ahead.frame_with(6, 4)[1] is None
    finally:
        ahead.close()
