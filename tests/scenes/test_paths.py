"""Lane paths and right turns (scenes/paths.py): poses along a lane, turn arcs inside the box."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnigen.scenes.generate import SceneGenerator
from omnigen.scenes.paths import Arc, lane_path, turn_path
from omnigen.scenes.placement import lane_crosses
from omnigen.scenes.shapes import to_world


@pytest.fixture(scope="module")
def city():
    return SceneGenerator("tiny", 3).city


def _right_turns(city):
    """(lane in, lane out, junction) of every right turn between rightmost driving lanes."""
    lanes = [ln for road in city.roads for ln in road.lanes if ln.kind == "driving"]
    out = []
    for junction in city.intersections:
        for a in lanes:
            for b in lanes:
                if (lane_crosses(a, junction) and lane_crosses(b, junction)
                        and math.cos(b.heading - (a.heading - math.pi / 2)) > 0.99):
                    out.append((a, b, junction))
    return out


def test_lane_path_pose_is_lane(city):
    lane = city.roads[0].lanes[0]
    s = np.array([0.0, 3.5, lane.length / 2, lane.length])
    x, y, yaw = lane_path(lane).pose_at(s)
    want = np.array([to_world(lane.start, lane.heading, v, 0.0) for v in s])
    assert np.allclose(np.stack([x, y], axis=1), want) and np.allclose(yaw, lane.heading)
    assert lane_path(lane).length == pytest.approx(lane.length)


def test_turn_arc_tangent_and_inside_box(city):
    turns = _right_turns(city)
    assert len(turns) >= 4
    for lane_in, lane_out, junction in turns:
        path = turn_path(lane_in, lane_out, junction)
        ends = np.cumsum([seg.length for seg in path.segments])[:-1]
        for e in ends:  # position and heading continuous where segments meet (tangent arc)
            x, y, yaw = path.pose_at(np.array([e - 1e-7, e + 1e-7]))
            assert abs(x[1] - x[0]) < 1e-5 and abs(y[1] - y[0]) < 1e-5
            assert abs(math.remainder(yaw[1] - yaw[0], 2 * math.pi)) < 1e-5
        arc = path.segments[1]
        assert isinstance(arc, Arc) and arc.radius > 0.5
        lo = path.segments[0].length
        x, y, _ = path.pose_at(np.linspace(lo, lo + arc.length, 50))
        cx, cy = junction.center
        hx, hy = junction.size[0] / 2 + 1e-6, junction.size[1] / 2 + 1e-6
        assert (np.abs(x - cx) <= hx).all() and (np.abs(y - cy) <= hy).all()
        x, y, yaw = path.pose_at(np.array([0.0, path.length]))
        assert np.allclose([x[0], y[0]], lane_in.start) and np.allclose([x[1], y[1]], lane_out.end, atol=1e-6)
        assert math.cos(yaw[0] - lane_in.heading) > 0.9999 and math.cos(yaw[1] - lane_out.heading) > 0.9999
