"""A sequence's moving world (scenes/world.py, motion.py, signals.py): instant 0 is the legacy
frame, the world is the same in any order and at any frame rate, and traffic is plausible."""

from __future__ import annotations

import math
import pickle
from dataclasses import replace

import numpy as np
import pytest
import shapely
from shapely.geometry import Point

from omnigen.scenes.description import to_json
from omnigen.scenes.generate import SceneGenerator, randomize_frame
from omnigen.scenes.motion import A_LIMIT, DT, LANE, V0, WALK
from omnigen.scenes.seeding import frame_streams, instant_extra_rng
from omnigen.scenes.shapes import rect_polygon
from omnigen.scenes.signals import GREEN, RED
from omnigen.scenes.generate import instant_zero
from omnigen.scenes.world import World

VEHICLES = {"car", "van", "truck", "bus", "tram", "motorcyclist", "cyclist", "tricyclist", "barrow"}


@pytest.fixture(scope="module")
def tiny():
    return SceneGenerator("tiny", 3)


@pytest.fixture(scope="module")
def junction():
    return SceneGenerator("intersection", 5)


def _world(gen, q: int) -> World:
    return World.build(gen.city, gen.preset, gen.seed, q)


def _foot(a):
    return rect_polygon(a.center[:2], a.dims[0], a.dims[1], a.yaw)


def test_instant_zero_is_placement(tiny):
    for q in (0, 4):
        world = _world(tiny, q)
        legacy = randomize_frame(tiny.city, tiny.preset, tiny.seed, q)
        scene = world.scene_at(0, fps=10.0)
        assert scene.agents == legacy.agents and scene.weather == legacy.weather and scene.lighting == legacy.lighting
        assert to_json(world.scene0) == to_json(legacy)  # a legacy frame's bytes
        assert len(scene.velocities) == len(scene.agents) and scene.instant == 0 and scene.time == 0.0


def test_same_world_any_order_any_fps(tiny):
    world = _world(tiny, 1)
    a = world.scene_at(5, fps=10.0)
    assert replace(a, instant=1) == world.scene_at(1, fps=2.0)
    later = world.scene_at(8, fps=10.0)
    assert world.scene_at(5, fps=10.0) == a  # asked again after a later instant (cursor restarts)
    fresh = _world(tiny, 1)
    assert fresh.scene_at(8, fps=10.0) == later
    assert to_json(fresh.scene_at(5, fps=10.0)) == to_json(a)
    # an fps whose instants fall between steps: still on the same world (blended steps)
    b = world.scene_at(3, fps=7.0)
    assert b.time == pytest.approx(3 / 7) and b == _world(tiny, 1).scene_at(3, fps=7.0)
    moved = [x for x, y in zip(world.scene_at(0, 10.0).agents, a.agents) if x.center != y.center]
    assert moved, "something moves in half a second"


def _lane_areas(city):
    areas = [rect_polygon(((ln.start[0] + ln.end[0]) / 2, (ln.start[1] + ln.end[1]) / 2), ln.length, ln.width + 0.2, ln.heading)
             for road in city.roads for ln in road.lanes if ln.kind in ("driving", "bike")]
    areas += [rect_polygon(i.center, i.size[0], i.size[1], 0.0) for i in city.intersections]
    return shapely.union_all(areas)


@pytest.mark.parametrize("preset,seed", [("tiny", s) for s in range(5)] + [("intersection", 2)])
def test_vehicles_keep_lanes_and_never_overlap(preset, seed):
    """Over 5 s no two footprints meet (vehicles, riders, walkers, parked cars and cones alike)
    and every moving agent stays on the carriageway: the intersection preset's junctions have
    traffic crossing the box from both roads at instant 0."""
    gen = SceneGenerator(preset, seed)
    world = World.build(gen.city, gen.preset, seed, 0)
    roads = _lane_areas(gen.city)
    moving = {a.instance_id for a in world.scene0.agents if a.state == "moving"}
    for k in range(0, 51):  # 5 s at 10 fps
        scene = world.scene_at(k, fps=10.0)
        feet = [_foot(a) for a in scene.agents]
        tree = shapely.STRtree(feet)
        i, j = tree.query(feet, predicate="intersects")
        pairs = [(scene.agents[p].instance_id, scene.agents[r].instance_id) for p, r in zip(i, j) if p < r]
        assert not pairs, f"seed {seed} t={k / 10}: footprints meet {pairs}"
        for a in scene.agents:
            if a.instance_id in moving:
                assert roads.contains(Point(a.center[:2])), f"seed {seed} t={k / 10}: {a.name} off the road"


def _next_stop(world, track):
    m = world.motion
    front = m.initial.s[track] + m.lane.half_l[track]
    ahead = np.nonzero(m.lane.stop_s[track] >= front - 1.0)[0]
    return None if not len(ahead) else ahead[0]


def test_queue_waits_for_red_then_goes(junction):
    world = _world(junction, 0)
    m = world.motion
    plans = list(m.plans)
    queued = []
    for t in range(len(m.lane.index)):
        j = _next_stop(world, t)
        if j is None or m.initial.v[t] != 0.0:
            continue
        sig = m.lane.stop_signal[t, j]
        plan, axis = plans[sig // 2], "xy"[sig % 2]
        if plan.state(axis, 0.0) == RED and m.lane.stop_s[t, j] - (m.initial.s[t] + m.lane.half_l[t]) < 3.0:
            queued.append((t, plan, axis))
    assert queued, "the intersection preset queues vehicles at red"
    t, plan, axis = queued[0]
    green_at = next(k * DT for k in range(1, 4000) if plan.state(axis, k * DT) == GREEN)
    while_red = int(green_at / DT) - 1
    assert m.state_at(while_red).s[t] == pytest.approx(m.initial.s[t], abs=1e-9)
    assert m.state_at(while_red).v[t] == 0.0
    assert m.state_at(while_red + int(6.0 / DT)).s[t] > m.initial.s[t] + 2.0, "the queue's front goes at green"


def test_signal_plans_agree_with_placed_queues(junction):
    scene0, phases = instant_zero(junction.city, junction.preset, junction.seed, 0)
    world = World.from_scene(scene0, phases)
    assert phases and set(phases) <= set(world.signals)
    for jid, green_x in phases.items():
        plan = world.signals[jid]
        assert plan.state("x" if green_x else "y", 0.0) == GREEN
        assert plan.state("y" if green_x else "x", 0.0) == RED


def test_speed_and_accel_bounds(junction):
    world = _world(junction, 1)
    m = world.motion
    vmax = np.array([V0.get(world.scene0.agents[i].category, (8.0, 14.0))[1] for i in m.lane.index])
    st = m.state_at(0)
    v_prev = st.v.copy()
    assert (v_prev <= vmax + 1e-9).all()
    for step in range(1, int(8.0 / DT) + 1):
        st = m.state_at(step)
        assert (st.v <= vmax + 1e-9).all() and (st.v >= 0).all()
        here = ~st.gone  # a track that left the city is no longer moved
        assert (np.abs(st.v - v_prev)[here] <= A_LIMIT * DT + 1e-9).all()
        v_prev = st.v.copy()
    prev = {a.instance_id: a.center for a in world.scene_at(0, 10.0).agents}
    for k in range(1, 81):
        now = {a.instance_id: a.center for a in world.scene_at(k, 10.0).agents}
        jumps = [math.dist(now[i][:2], prev[i][:2]) / 0.1 for i in now if i in prev]
        assert max(jumps) <= 40.0
        prev = now


def test_velocity_is_the_motion(tiny):
    world = _world(tiny, 2)
    fps = 20.0
    for k in (5, 30):
        before, now, after = (world.scene_at(i, fps) for i in (k - 1, k, k + 1))
        b = {a.instance_id: a.center for a in before.agents}
        f = {a.instance_id: a.center for a in after.agents}
        yaw_after = {a.instance_id: a.yaw for a in after.agents}
        turned = {x.instance_id for x in before.agents if math.cos(x.yaw - yaw_after.get(x.instance_id, x.yaw)) < 0}
        for a, v in zip(now.agents, now.velocities):
            if a.instance_id in b and a.instance_id in f and a.instance_id not in turned:  # not a walker turning round
                fd = np.subtract(f[a.instance_id][:2], b[a.instance_id][:2]) * fps / 2
                assert np.linalg.norm(fd - v[:2]) < 0.5, a.name
    assert any(np.linalg.norm(v) > 1.0 for v in now.velocities)


def test_parked_and_cones_stay(tiny):
    world = _world(tiny, 0)
    still = {a.instance_id: a for a in world.scene0.agents if a.state in ("parked", "placed", "standing")}
    assert any(a.category == "traffic_cone" for a in still.values()) and any(a.state == "parked" for a in still.values())
    later = {a.instance_id: a for a in world.scene_at(50, 10.0).agents}
    assert all(later[i] == a for i, a in still.items())


def test_walkers_stay_on_their_strip(tiny):
    world = _world(tiny, 3)
    city = tiny.city
    strips = [rect_polygon(s.center, s.length, s.width, s.yaw) for s in city.sidewalks if s.kind == "sidewalk"]
    strips += [rect_polygon(c.center, c.length, c.width, c.yaw) for c in city.crosswalks]
    m = world.motion
    walkers = {world.scene0.agents[i].instance_id for i in m.walk.index}
    assert walkers
    home = {}
    for k in range(0, 301, 10):  # 30 s: long enough to reach a strip's end and turn
        for a in world.scene_at(k, 10.0).agents:
            if a.instance_id in walkers:
                inside = {n for n, s in enumerate(strips) if s.buffer(0.05).contains(Point(a.center[:2]))}
                home.setdefault(a.instance_id, inside)
                assert home[a.instance_id] & inside, f"{a.name} left its strip at t={k / 10}"
    assert any(m.state_at(300).d != m.initial.d), "some walker turned round at its strip's end"


def test_some_vehicle_turns_right(tiny):
    for q in range(8):
        world = _world(tiny, q)
        m = world.motion
        turning = np.nonzero(m.lane.turns)[0]
        for t in turning:
            i = m.lane.index[t]
            yaw0 = world.scene0.agents[i].yaw
            for step in range(0, int(40.0 / DT), 20):
                pose = m.poses(m.state_at(step), step * DT)
                if not pose.present[i]:
                    break
                if math.cos(pose.yaw[i] - (yaw0 - math.pi / 2)) > 0.999:
                    return  # headed 90 degrees right of where it started
    pytest.fail("no vehicle turned right in 8 sequences")


def _held(motion) -> int:
    """Bytes a rollout holds: everything the motion keeps, its cursor state counted by array size
    (a pickle's length would vary by a few bytes with the numbers it holds)."""
    rest = {k: v for k, v in vars(motion).items() if k != "_cursor"}
    arrays = [v for v in vars(motion._cursor).values() if isinstance(v, np.ndarray)]
    return len(pickle.dumps(rest)) + sum(x.nbytes for x in arrays) + len(vars(motion._cursor))


def test_rollout_keeps_no_history(tiny):
    world = _world(tiny, 0)
    world.scene_at(10, 10.0)
    small = _held(world.motion)
    world.scene_at(1000, 10.0)
    assert _held(world.motion) == small
    assert world.motion.state_at(2000).step == 2000


def test_walkers_and_lanes_classified(tiny):
    world = _world(tiny, 0)
    kinds = {LANE: world.motion.lane.index, WALK: world.motion.walk.index}
    states = {k: {world.scene0.agents[i].state for i in v} for k, v in kinds.items()}
    assert states[LANE] == {"moving"} and states[WALK] <= {"walking", "crossing"}


def test_extra_stream_at_instant_zero_is_frame_extra():
    want = frame_streams(11, 4)["extra"].random(5)
    assert np.array_equal(instant_extra_rng(11, 4, 0).random(5), want)
    assert not np.array_equal(instant_extra_rng(11, 4, 1).random(5), want)


def test_track_leaves_at_its_paths_end(tiny):
    """A vehicle whose path ends (at the city's bound) drops out of later Scenes for good."""
    for q in range(6):
        world = _world(tiny, q)
        m = world.motion
        left = m.lane.length - m.initial.s
        t = int(np.argmin(left))
        if left[t] > 30.0:
            continue
        iid = world.scene0.agents[m.lane.index[t]].instance_id
        ids = [{a.instance_id for a in world.scene_at(k, 2.0).agents} for k in range(0, 41)]  # 20 s
        gone = [iid not in x for x in ids]
        assert not gone[0] and gone[-1], "it drives off within 20 s"
        k = gone.index(True)
        assert all(gone[k:]), "and never comes back"
        return
    pytest.fail("no vehicle within 30 m of its path's end")
