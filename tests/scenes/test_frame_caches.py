"""The per-frame shortcuts (issue 26's speed margin) give exactly what the plain code gives.

- `canonical` of an Agent skips the to_dict/from_dict round trip: the result must be the very
  object the round trip makes (same types: tuples, not lists; floats, not ints; -0.0 as 0.0);
- placement and the camera's obstacles keep what a fixed city alone decides (its obstacles, lane
  and junction geometry) across frames: a frame must come out the same whether the city's cache
  is fresh or already used by other frames, and what one frame adds must not leak into the next.
"""

from __future__ import annotations

import copy

import numpy as np
import shapely
import pytest

from omnigen.scenes.description import Agent, AssetSpec, canonical, from_dict, to_dict, to_json
from omnigen.scenes.generate import SceneGenerator
from omnigen.scenes.placement import place_agents
from omnigen.scenes.seeding import frame_streams


def _round_trip(obj):
    return from_dict(type(obj), to_dict(obj))


@pytest.mark.parametrize("preset", ["downtown", "intersection"])
def test_canonical_agent_is_the_round_trip(preset):
    gen = SceneGenerator(preset, 3)
    for index in (0, 1):
        agents = place_agents(gen.city, gen.preset.agents, frame_streams(3, index)["agents"], gen.user_assets)
        assert len(agents) > 10
        for a in agents:
            fast, slow = canonical(a), _round_trip(a)
            assert fast == slow and repr(fast) == repr(slow), a.name


def test_canonical_agent_odd_values():
    """Values placement does not make today but a user asset or a future family might."""
    params = {"paint": (0.1234567891, -1e-9, 1.0), "nested": {"a": [1, 2.5e-7, (3, "x")], 2: None},
              "flag": True, "n": 3, "np": np.float64(0.30000000049),
              "npint": np.int64(4), "text": "s"}
    odd = [
        Agent(7, "car", (1.0000004, -2e-9, 0.7), (4.2, 1.8, 1.5), -3.1415926535, "moving", AssetSpec("car", params)),
        Agent(np.int64(8), "car", (np.float64(1.23456789), 2.0, 3.0), (1, 2, 3), np.float64(0.5), "parked", AssetSpec("car", {})),
        Agent(9, "car", [1.0, 2.0, 3.0], [4.0, 2.0, 1.5], 0.0, "moving", AssetSpec("car", {})),
    ]
    for a in odd:
        fast, slow = canonical(a), _round_trip(a)
        assert repr(fast) == repr(slow)
        assert to_json(fast) == to_json(slow)
    bad = Agent(10, "car", (1.0, 2.0), (4.0, 2.0, 1.5), 0.0, "moving", AssetSpec("car", {}))
    with pytest.raises(ValueError):
        canonical(bad)


def test_placement_same_with_a_fresh_or_used_city_cache():
    gen = SceneGenerator("downtown", 5)
    spec = gen.preset.agents

    def frame(city, index):
        return to_json(place_agents(city, spec, frame_streams(5, index)["agents"]))

    used = [frame(gen.city, i) for i in (0, 1, 2, 3)]  # one city object: its cache is built, then reused
    fresh = copy.deepcopy(gen.city)  # an equal city, another object: a cache of its own
    assert frame(fresh, 3) == used[3]
    assert frame(fresh, 0) == used[0]
    assert frame(gen.city, 2) == used[2]  # frames 0..3 added cones and work zones: nothing leaked
    assert len(set(used)) == 4


def test_camera_obstacles_same_with_a_fresh_or_used_city_cache():
    from omnigen.rigs.rig import load_rig
    from omnigen.rigs.sampling import Obstacles, rig_rng, sample_camera

    gen = SceneGenerator("downtown", 2)
    rig = load_rig("ego")
    scenes = [gen.frame(2, i) for i in range(3)]

    def poses(scene):
        out = []
        for i in range(3):
            cam = sample_camera(rig, scene, rig_rng(2, i), 320, 240, Obstacles(scene))
            out.append((cam.K.tobytes(), cam.R.tobytes(), cam.t.tobytes(), cam.tries))
        return out

    used = [poses(s) for s in scenes]
    fresh = copy.deepcopy(scenes[2])  # another city object: its static obstacles built anew
    assert poses(fresh) == used[2]
    # the static layer is shared, the agents' layer is the frame's own: frames differ in it
    assert Obstacles(scenes[0]).layers[0] is Obstacles(scenes[1]).layers[0]
    agents = [[shapely.to_wkb(p) for p in Obstacles(s).layers[1].polys] for s in scenes[:2]]
    assert agents[0] != agents[1]


def test_agent_footprints_are_the_affine_transform_of_their_box():
    """The camera's agent layer builds every footprint at once; each must be the very polygon
    the per-agent shapely.affinity call makes (same vertices, same order, same bits)."""
    import math

    import shapely

    from omnigen.rigs.sampling import _agent_layer

    gen = SceneGenerator("intersection", 4)
    agents = gen.frame(4, 1).agents
    layer = _agent_layer(agents)
    assert len(layer.polys) == len(agents) > 10
    for a, poly in zip(agents, layer.polys):
        box = shapely.box(-a.dims[0] / 2, -a.dims[1] / 2, a.dims[0] / 2, a.dims[1] / 2)
        c, s = math.cos(a.yaw), math.sin(a.yaw)
        assert shapely.to_wkb(poly) == shapely.to_wkb(shapely.affinity.affine_transform(box, [c, -s, s, c, a.center[0], a.center[1]]))
    assert list(layer.tops) == [a.center[2] + a.dims[2] / 2 for a in agents]
    assert len(_agent_layer(()).polys) == 0
