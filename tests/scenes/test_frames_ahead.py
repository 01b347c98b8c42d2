"""Frames drawn ahead in a second process (issue 48) are the frames drawn here: the same agents,
weather and light (to the byte of their JSON), on this process's city object."""

from __future__ import annotations

import os
import signal

import pytest

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


def _drawn_ahead_with_meshes(monkeypatch) -> tuple[SceneGenerator, object]:
    """Frame 2 of the tiny city drawn by a FramesAhead worker that builds its meshes, adopted
    into an empty mesh cache."""
    from omnigen.scenes.assets import build

    monkeypatch.setattr(build, "_CACHE", type(build._CACHE)())
    gen = SceneGenerator("tiny", 6)
    ahead = FramesAhead(gen, meshes=True)
    try:
        ahead.ask(6, 2)
        scene = ahead.frame(6, 2)
    finally:
        ahead.close()
    return gen, scene


def test_meshes_built_ahead_are_adopted_and_equal_a_build_here(monkeypatch):
    """With meshes=True the worker builds the frame's agent meshes and this process adopts them:
    agent_parts then builds nothing (no builder is reachable) and gives the very arrays a build
    here gives. Without it the worker's meshes are not sent (the raster builds only agents in view)."""
    from omnigen.scenes.assets import build

    gen, scene = _drawn_ahead_with_meshes(monkeypatch)
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


def test_the_keys_of_adopted_meshes_are_the_workers_and_equal_those_made_here(monkeypatch):
    """The worker's keys of a frame's agents are known to this process after adoption: agent_parts
    makes no JSON key for them, and each equals the key made here; an asset that was not adopted
    (another object, even an equal one) has its key made."""
    import copy
    import json

    from omnigen.scenes.assets import build

    _, scene = _drawn_ahead_with_meshes(monkeypatch)
    with monkeypatch.context() as m:
        m.setattr(build, "json", None)  # no key can be made: each must be known
        known = [build._agent_key(a.asset, a.dims) for a in scene.agents]
        parts = [build.agent_parts(a.asset, a.dims) for a in scene.agents]
    assert known and known == [json.dumps([build.to_dict(a.asset), build.to_dict(tuple(a.dims))], sort_keys=True)
                               for a in scene.agents]
    assert all(p is build._CACHE[k] for p, k in zip(parts, known))
    other = copy.deepcopy(scene.agents[0].asset)
    with monkeypatch.context() as m, pytest.raises(AttributeError):
        m.setattr(build, "json", None)
        build._agent_key(other, scene.agents[0].dims)
    assert build._agent_key(other, scene.agents[0].dims) == known[0]


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
