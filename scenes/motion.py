"""How a sequence's agents move: a deterministic rollout on a fixed step, from instant 0's placement.

Kinds (by the state placement gave each agent):
- still: parked vehicles, cones and standing people never move;
- lane: moving vehicles, trams, riders and road barrows follow a path (scenes/paths.py: their lane,
  or a right turn at their next junction) with the Intelligent Driver Model. The leader is the
  nearest footprint of any agent ahead in the track's corridor (its width plus a margin, up to
  LOOKAHEAD metres, in the frame of its path tangent), so following, queueing, waiting for a
  pedestrian on a crosswalk and stopping behind cones are one rule; a red (or amber, when the track
  can still stop at A_LIMIT) signal ahead is a standing leader at its stop line;
- walk: walkers go straight along their sidewalk strip (the road's direction) or crosswalk at a
  constant speed, wait while something stands within WALK_GAP ahead, and turn round at the end.

Why a fixed step (DT) and interpolation: the world must not depend on the frame rate it is seen
at, nor on the order instants are asked for; instant k at fps F is time k / F, between two steps.
Why no history: `Motion.state_at` steps a single cursor forward (starting again from t = 0 only
for an earlier time), so memory stays flat over any number of instants.
Placement's lateral offset and yaw noise decay over KEEP_M metres driven (lane keeping; a vehicle
standing still does not turn), a walker's yaw noise over TAU seconds, so instant 0 is placement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from omnigen.scenes.description import Agent, City, Lane, Vec3
from omnigen.scenes.paths import Path, along, lane_path, turn_path
from omnigen.scenes.placement import lane_crosses, lane_span
from omnigen.scenes.signals import AMBER, RED, STOP_BEFORE_BOX, SignalPlan

DT = 0.05  # seconds a step
A_LIMIT = 4.0  # m/s^2: no track brakes or accelerates harder
LOOKAHEAD = 40.0  # metres a lane track looks for its leader
CORRIDOR_MARGIN = 0.25  # metres either side of a lane track's width
WALK_GAP = 0.5  # metres a walker keeps free ahead
FORESIGHT = 3.0  # seconds of the way of a walker, or of a crossing track with the right of way, kept clear
CROSSING_COS = 0.7  # |cos| of the heading difference below which two tracks cross rather than follow
TAU = 1.0  # seconds: a walker's yaw noise from placement decays
KEEP_M = 8.0  # metres driven: a lane track's offset and yaw noise from placement decay (about TAU at 8 m/s)
S0 = 2.0  # metres: IDM standstill gap
TURN_PROBABILITY = 0.25  # a rightmost-lane vehicle turns right at its next junction

# Desired speed (m/s) by class: city traffic; riders and barrows at their own pace.
V0 = {"car": (8.0, 14.0), "van": (8.0, 14.0), "truck": (7.0, 11.0), "bus": (7.0, 11.0), "tram": (7.0, 11.0),
      "motorcyclist": (9.0, 15.0), "cyclist": (3.0, 6.0), "tricyclist": (2.5, 5.0), "barrow": (1.0, 1.5)}
V0_DEFAULT = (8.0, 14.0)
RIDERS = {"cyclist", "tricyclist", "barrow"}  # placed by a lane's edge: they keep to it
STILL, LANE, WALK = 0, 1, 2
_KIND = {"moving": LANE, "walking": WALK, "crossing": WALK}


@dataclass(frozen=True)
class LaneTracks:
    """The lane tracks' fixed parameters, parallel arrays over them (`index` into the agents)."""

    index: np.ndarray
    paths: tuple[Path, ...]
    path_of: np.ndarray  # which of `paths` each track follows (tracks of one lane share it)
    length: np.ndarray  # of each track's path
    half_l: np.ndarray
    half_w: np.ndarray
    v0: np.ndarray
    a_max: np.ndarray
    b: np.ndarray
    headway: np.ndarray
    offset0: np.ndarray  # lateral offset from the path at t = 0 (decays with KEEP_M unless `keeps_edge`)
    yaw0: np.ndarray  # yaw off the path tangent at t = 0 (decays with KEEP_M)
    keeps_edge: np.ndarray  # riders keep the line placement gave them (by the lane's right edge)
    stop_s: np.ndarray  # (tracks, K) stop lines along the path, inf-padded
    stop_signal: np.ndarray  # (tracks, K) index into the signal states (plan x 2 + axis y), -1 pad
    turns: np.ndarray  # whether the track turns right


@dataclass(frozen=True)
class WalkTracks:
    """Walkers: a line through the start along `axis`, `u` in [lo, hi] on it."""

    index: np.ndarray
    origin: np.ndarray  # (w, 2) the strip's centre shifted across to the walker's line
    axis: np.ndarray  # (w, 2) unit
    lo: np.ndarray
    hi: np.ndarray
    speed: np.ndarray
    yaw0: np.ndarray


@dataclass
class MotionState:
    """Everything that changes: fixed-size arrays, so a rollout's memory never grows."""

    step: int
    s: np.ndarray  # lane tracks: arc length along the path
    v: np.ndarray  # lane tracks: speed
    gone: np.ndarray  # lane tracks past their path's end (left the city)
    u: np.ndarray  # walkers: position along the axis
    d: np.ndarray  # walkers: +1 or -1 along the axis
    pace: np.ndarray  # walkers: speed this step (below their own behind someone slower, 0 waiting)


@dataclass(frozen=True)
class Poses:
    """Every agent's centre (x, y), yaw, world velocity (vx, vy) and presence at one time."""

    xy: np.ndarray
    yaw: np.ndarray
    vel: np.ndarray
    present: np.ndarray


class Motion:
    """A sequence's motion: fixed parameters plus a cursor state stepped forward on demand."""

    def __init__(self, agents: tuple[Agent, ...], lane: LaneTracks, walk: WalkTracks, plans: tuple[SignalPlan, ...],
                 initial: MotionState) -> None:
        self.agents, self.lane, self.walk, self.plans = agents, lane, walk, plans
        n = len(agents)
        self.xy0 = np.array([a.center[:2] for a in agents], dtype=np.float64).reshape(n, 2)
        self.yaw_still = np.array([a.yaw for a in agents], dtype=np.float64)
        self.half = np.array([(a.dims[0] / 2, a.dims[1] / 2) for a in agents], dtype=np.float64).reshape(n, 2)
        self.walker = np.zeros(n, dtype=bool)  # which agents are walkers (_right_of_way, every step)
        self.walker[walk.index] = True
        self.initial = initial
        self._cursor = _copy(initial)

    def state_at(self, step: int) -> MotionState:
        """The state after `step` steps: from the cursor, or from t = 0 for an earlier step."""
        if step < self._cursor.step:
            self._cursor = _copy(self.initial)
        while self._cursor.step < step:
            self._cursor = self.advance(self._cursor)
        return self._cursor

    def poses_at(self, t: float) -> Poses:
        """Poses at `t` seconds: the state at the step before, blended with the next when t falls
        between steps (so any frame rate sees the one world)."""
        n = t / DT
        k = int(round(n))
        if abs(n - k) < 1e-9:
            return self.poses(self.state_at(k), k * DT)
        k = int(math.floor(n))
        a = self.poses(self.state_at(k), k * DT)  # posed before the cursor moves on (a step makes new arrays)
        b = self.poses(self.state_at(k + 1), (k + 1) * DT)
        f = n - k
        dyaw = np.arctan2(np.sin(b.yaw - a.yaw), np.cos(b.yaw - a.yaw))
        return Poses(a.xy + f * (b.xy - a.xy), a.yaw + f * dyaw, a.vel + f * (b.vel - a.vel), a.present & b.present)

    # -- the step ---------------------------------------------------------------------------

    def poses(self, st: MotionState, t: float) -> Poses:
        xy, yaw = self.xy0.copy(), self.yaw_still.copy()
        vel = np.zeros_like(xy)
        present = np.ones(len(self.agents), dtype=bool)
        L, W = self.lane, self.walk
        if len(L.index):
            px, py, pyaw = _path_poses(L.paths, L.path_of, st.s)
            decay = np.exp(-(st.s - self.initial.s) / KEEP_M)
            off = L.offset0 * np.where(L.keeps_edge, 1.0, decay)
            nx, ny = -np.sin(pyaw), np.cos(pyaw)
            xy[L.index, 0], xy[L.index, 1] = px + off * nx, py + off * ny
            yaw[L.index] = pyaw + L.yaw0 * decay
            doff = np.where(L.keeps_edge, 0.0, -off * st.v / KEEP_M)  # d(offset)/dt
            vel[L.index, 0] = st.v * np.cos(pyaw) + doff * nx
            vel[L.index, 1] = st.v * np.sin(pyaw) + doff * ny
            present[L.index] = ~st.gone
        if len(W.index):
            xy[W.index] = W.origin + st.u[:, None] * W.axis
            base = np.arctan2(W.axis[:, 1], W.axis[:, 0]) + np.where(st.d > 0, 0.0, math.pi)
            yaw[W.index] = base + W.yaw0 * math.exp(-t / TAU)
            vel[W.index] = (st.d * st.pace)[:, None] * W.axis
        return Poses(xy, np.arctan2(np.sin(yaw), np.cos(yaw)), vel, present)

    def signal_states(self, t: float) -> np.ndarray:
        """Per (plan, axis) at `t`: 0 green, 1 amber, 2 red; flattened as plan * 2 + (axis == "y")."""
        code = {AMBER: 1, RED: 2}
        return np.array([code.get(p.state(ax, t), 0) for p in self.plans for ax in ("x", "y")], dtype=np.int8)

    def lane_gaps(self, st: MotionState, t: float, pose: Poses) -> tuple[np.ndarray, np.ndarray]:
        """(gap to the leader, the leader's speed along the track) for every lane track: the
        nearest footprint ahead in its corridor, or the stop line of a red signal ahead."""
        L = self.lane
        gap, lead_v = _leaders(self, pose, L.index, L.half_l, L.half_w + CORRIDOR_MARGIN, LOOKAHEAD, foresee=True)
        if L.stop_s.shape[1] and self.plans:
            states = self.signal_states(t)
            front = st.s + L.half_l
            ahead = L.stop_s >= front[:, None] - 1.0  # a track whose nose passed a line by 1 m is committed
            first = np.argmax(ahead, axis=1)
            rows = np.arange(len(front))
            has = ahead[rows, first] & (L.stop_signal[rows, first] >= 0)
            sig = np.where(has, states[np.maximum(L.stop_signal[rows, first], 0)], 0)
            to_line = L.stop_s[rows, first] - front
            can_stop = st.v ** 2 / (2 * A_LIMIT) <= np.maximum(to_line, 0.0) + 0.5
            stop = has & ((sig == 2) | ((sig == 1) & can_stop))
            closer = stop & (to_line < gap)
            gap = np.where(closer, to_line, gap)
            lead_v = np.where(closer, 0.0, lead_v)
        return gap, lead_v

    def advance(self, st: MotionState) -> MotionState:
        """One DT step: IDM for lane tracks, walking for walkers."""
        t = st.step * DT
        pose = self.poses(st, t)
        s, v, gone = st.s, st.v, st.gone
        L = self.lane
        if len(L.index):
            gap, lead_v = self.lane_gaps(st, t, pose)
            acc = idm(v, L.v0, L.a_max, L.b, L.headway, gap, v - lead_v)
            v_new = np.clip(v + acc * DT, 0.0, L.v0)
            v_new = np.where(gone, 0.0, v_new)
            s = s + 0.5 * (v + v_new) * DT
            v, gone = v_new, gone | (s > L.length)
        u, d, pace = st.u, st.d, st.pace
        W = self.walk
        if len(W.index):
            gap, lead_v = _leaders(self, pose, W.index, self.half[W.index, 0], self.half[W.index, 1] + 0.1, WALK_GAP + 2.0,
                                   foresee=False)
            # Close up to WALK_GAP behind what is ahead within a second, never faster than its own
            # pace: a walker behind a slower one keeps its distance instead of stopping and going.
            pace = np.clip(np.minimum(W.speed, np.maximum(lead_v, 0.0) + gap - WALK_GAP), 0.0, W.speed)
            u = u + d * pace * DT
            over, under = u > W.hi, u < W.lo
            u = np.where(over, 2 * W.hi - u, np.where(under, 2 * W.lo - u, u))
            d = np.where(over, -1.0, np.where(under, 1.0, d))
        return MotionState(st.step + 1, s, v, gone, u, d, pace)


def idm(v, v0, a_max, b, headway, gap, dv) -> np.ndarray:
    """Intelligent Driver Model acceleration, cut to [-A_LIMIT, a_max]; gap = inf: free road."""
    s_star = S0 + np.maximum(0.0, v * headway + v * dv / (2.0 * np.sqrt(a_max * b)))
    inter = np.where(np.isfinite(gap), (s_star / np.maximum(gap, 0.05)) ** 2, 0.0)
    return np.clip(a_max * (1.0 - (v / v0) ** 4 - inter), -A_LIMIT, a_max)


def _copy(st: MotionState) -> MotionState:
    return MotionState(st.step, st.s.copy(), st.v.copy(), st.gone.copy(), st.u.copy(), st.d.copy(), st.pace.copy())


def _path_poses(paths: tuple[Path, ...], path_of: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """pose_at for every lane track (track i at s[i] on paths[path_of[i]]), one call per distinct path."""
    x, y, yaw = np.empty_like(s), np.empty_like(s), np.empty_like(s)
    for k, path in enumerate(paths):
        m = path_of == k
        if m.any():
            x[m], y[m], yaw[m] = path.pose_at(s[m])
    return x, y, yaw


def _leaders(motion: Motion, pose: Poses, which: np.ndarray, half_l: np.ndarray, half_corridor: np.ndarray,
             reach: float, foresee: bool) -> tuple[np.ndarray, np.ndarray]:
    """For each agent in `which`: the gap from its nose to the nearest other present footprint
    ahead (within `reach`) whose extent across its heading meets its corridor, and that agent's
    speed along the heading; (inf, 0) when none. With `foresee`, the footprint of a walker (it
    may step in) or of a track crossing this one's way that reaches the crossing first (it has the
    right of way) counts as the box over where it is and where it will be in FORESIGHT seconds:
    of two tracks converging in a junction box one yields, and neither runs into the other.

    Why pairs first: only agents whose centres lie within reach can matter, a few per track, so
    footprints are projected for those pairs alone (a junction holds hundreds of agents)."""
    m = len(which)
    best, lead_v = np.full(m, np.inf), np.zeros(m)
    if not m:
        return best, lead_v
    ext = FORESIGHT * pose.vel if foresee else np.zeros_like(pose.vel)
    radius = np.hypot(motion.half[:, 0], motion.half[:, 1]) + np.hypot(ext[:, 0], ext[:, 1])
    dist = np.hypot(*(pose.xy[None, :, :] - pose.xy[which][:, None, :]).transpose(2, 0, 1))
    near = (dist < (reach + half_l + half_corridor)[:, None] + radius[None, :]) & pose.present[None, :]
    near[np.arange(m), which] = False
    ii, jj = np.nonzero(near)
    if not len(ii):
        return best, lead_v
    corners = _corners(pose.xy[jj], pose.yaw[jj], motion.half[jj])  # (p, 4, 2)
    c, s = np.cos(pose.yaw[which][ii]), np.sin(pose.yaw[which][ii])
    if foresee:
        ahead = _right_of_way(motion, pose, which[ii], jj, c, s)
        corners = np.concatenate([corners, corners + (ext[jj] * ahead[:, None])[:, None, :]], axis=1)
    rel = corners - pose.xy[which][ii][:, None, :]
    fwd = rel[..., 0] * c[:, None] + rel[..., 1] * s[:, None]
    lat = -rel[..., 0] * s[:, None] + rel[..., 1] * c[:, None]
    hl, hc = half_l[ii], half_corridor[ii]
    a_lo = fwd.min(axis=1)
    hit = (lat.max(axis=1) > -hc) & (lat.min(axis=1) < hc) & (fwd.max(axis=1) > hl - 0.3) & (a_lo < hl + reach)
    if not hit.any():
        return best, lead_v
    ii, jj, c, s = ii[hit], jj[hit], c[hit], s[hit]
    gap = np.maximum(a_lo[hit] - hl[hit], 0.0)
    order = np.lexsort((gap, ii))  # by track, nearest first
    first = order[np.r_[True, ii[order][1:] != ii[order][:-1]]]
    best[ii[first]] = gap[first]
    lead_v[ii[first]] = pose.vel[jj[first], 0] * c[first] + pose.vel[jj[first], 1] * s[first]
    return best, lead_v


def _right_of_way(motion: Motion, pose: Poses, i: np.ndarray, j: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """For pairs (i, j): whether i must keep clear of where j is going. Walkers always; a lane
    track crossing i's heading when it reaches the crossing of their headings no later than i
    (time to it at its speed, 0.5 m/s at least; ties to the lower index); following traffic never
    (car following handles it)."""
    cj, sj = np.cos(pose.yaw[j]), np.sin(pose.yaw[j])
    cross = c * sj - s * cj  # sin of the heading difference
    crossing = np.abs(c * cj + s * sj) < CROSSING_COS
    d = pose.xy[j] - pose.xy[i]
    safe = np.where(np.abs(cross) > 1e-6, cross, 1.0)
    ti = (d[:, 0] * sj - d[:, 1] * cj) / safe  # along i's heading to the crossing point
    tj = (d[:, 0] * s - d[:, 1] * c) / safe  # along j's heading to it
    speed = np.maximum(np.hypot(pose.vel[:, 0], pose.vel[:, 1]), 0.5)
    first = (tj / speed[j] < ti / speed[i]) | ((tj / speed[j] == ti / speed[i]) & (j < i))
    return motion.walker[j] | (crossing & (ti > 0) & (tj > -motion.half[j, 0]) & first)


def _corners(xy: np.ndarray, yaw: np.ndarray, half: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[1, -1], [1, 1], [-1, 1], [-1, -1]], dtype=np.float64)  # (4, 2) in half units
    lx, ly = local[None, :, 0] * half[:, 0:1], local[None, :, 1] * half[:, 1:2]
    return np.stack([xy[:, 0:1] + lx * c[:, None] - ly * s[:, None], xy[:, 1:2] + lx * s[:, None] + ly * c[:, None]], axis=-1)


# -- drawing a sequence's motion --------------------------------------------------------------


def _lane_of(agent: Agent, lanes: list[Lane]) -> Lane | None:
    """The driving or bike lane the agent stands in, heading its way (None: none fits)."""
    best, best_off = None, math.inf
    for lane in lanes:
        if math.cos(agent.yaw - lane.heading) < 0.9:
            continue
        t = along(lane, agent.center)
        off = abs(-(agent.center[0] - lane.start[0]) * math.sin(lane.heading) + (agent.center[1] - lane.start[1]) * math.cos(lane.heading))
        if 0.0 <= t <= lane.length and off <= lane.width / 2 and off < best_off:
            best, best_off = lane, off
    return best


def _turn(lane: Lane, s0: float, half_l: float, city: City, rightmost: set[str], driving: list[Lane]):
    """(lane out, junction) of a right turn at the lane's next junction ahead, or None."""
    if lane.lane_id not in rightmost:
        return None
    spans = sorted((lane_span(lane, i), i) for i in city.intersections if lane_crosses(lane, i))
    ahead = [(a, i) for (a, _), i in spans if a > s0 + half_l + 1.0]
    if not ahead:
        return None
    _, junction = ahead[0]
    right = lane.heading - math.pi / 2
    for out in driving:
        if out.lane_id in rightmost and math.cos(out.heading - right) > 0.99 and lane_crosses(out, junction):
            return out, junction
    return None


def _stops(lane: Lane, turn, city: City, plan_ids: dict[str, int]) -> list[tuple[float, int]]:
    """(stop line along the route, signal index) of each signalised junction the route enters."""
    def on(ln: Lane, lo: float, shift: float):
        out = []
        for i in city.intersections:
            if i.intersection_id in plan_ids and lane_crosses(ln, i):
                a, _ = lane_span(ln, i)
                if a >= lo:
                    axis = 0 if abs(math.cos(ln.heading)) > 0.5 else 1
                    out.append((a - STOP_BEFORE_BOX + shift, plan_ids[i.intersection_id] * 2 + axis))
        return out
    if turn is None:
        return sorted(on(lane, -math.inf, 0.0))
    out_lane, junction = turn
    path = turn_path(lane, out_lane, junction)
    first, arc = path.segments[0], path.segments[1]
    t2 = along(out_lane, path.segments[2].start)
    before = [x for x in on(lane, -math.inf, 0.0) if x[0] < first.length]
    return sorted(before + on(out_lane, t2, first.length + arc.length - t2))


def draw_motion(agents: tuple[Agent, ...], city: City, plans: dict[str, SignalPlan], rng: np.random.Generator) -> Motion:
    """A sequence's motion from its instant-0 agents: parameters, routes and walkers drawn from
    `rng` (the sequence's motion stream) in agent order, the same numbers for any plan."""
    lanes = [ln for road in city.roads for ln in road.lanes if ln.kind in ("driving", "bike")]
    driving = [ln for ln in lanes if ln.kind == "driving"]
    rightmost = {ln.lane_id for road in city.roads for ln in road.lanes if ln.kind == "driving"
                 and not any(o.kind == "driving" and o.lane_id[:-1] == ln.lane_id[:-1] and o.lane_id > ln.lane_id for o in road.lanes)}
    plan_list = tuple(plans.values())
    plan_ids = {p.junction_id: k for k, p in enumerate(plan_list)}
    kinds = [_KIND.get(a.state, STILL) for a in agents]
    n_lane = sum(k == LANE for k in kinds)
    # Every lane-kind agent draws its numbers whether or not it finds a lane: fixed per agent.
    u = rng.random((n_lane, 6))
    walkers = [i for i, k in enumerate(kinds) if k == WALK]
    walk_speed = rng.uniform(1.0, 1.6, len(walkers))
    lane_rows, path_keys, paths, path_of = [], {}, [], []
    for k, i in enumerate(i for i, kd in enumerate(kinds) if kd == LANE):
        a = agents[i]
        lane = _lane_of(a, lanes)
        if lane is None:
            kinds[i] = STILL  # placed off every lane (not by this placement): stands
            continue
        s0 = along(lane, a.center)
        turn = _turn(lane, s0, a.dims[0] / 2, city, rightmost, driving) if a.category != "tram" and u[k, 5] < TURN_PROBABILITY else None
        key = (lane.lane_id, None if turn is None else turn[0].lane_id)
        if key not in path_keys:
            path_keys[key] = len(paths)
            paths.append(lane_path(lane) if turn is None else turn_path(lane, *turn))
        path_of.append(path_keys[key])
        lane_rows.append((i, k, lane, s0, turn))
    idx = np.array([r[0] for r in lane_rows], dtype=np.int64)
    uu = u[[r[1] for r in lane_rows]] if lane_rows else np.zeros((0, 6))
    lo_hi = np.array([V0.get(agents[i].category, V0_DEFAULT) for i in idx], dtype=np.float64).reshape(-1, 2)
    v0 = lo_hi[:, 0] + uu[:, 0] * (lo_hi[:, 1] - lo_hi[:, 0])
    s0 = np.array([r[3] for r in lane_rows], dtype=np.float64)
    path_of_a = np.array(path_of, dtype=np.int64)
    px, py, pyaw = _path_poses(paths, path_of_a, s0)
    cx = np.array([agents[i].center[0] for i in idx]) - px
    cy = np.array([agents[i].center[1] for i in idx]) - py
    yaw = np.array([agents[i].yaw for i in idx])
    stops = [_stops(r[2], r[4], city, plan_ids) for r in lane_rows]
    width = max((len(x) for x in stops), default=0)
    stop_s = np.full((len(idx), width), np.inf)
    stop_sig = np.full((len(idx), width), -1, dtype=np.int64)
    for k, x in enumerate(stops):
        for j, (ss, sig) in enumerate(x):
            stop_s[k, j], stop_sig[k, j] = ss, sig
    lane_tracks = LaneTracks(
        idx, tuple(paths), path_of_a, np.array([p.length for p in paths])[path_of_a] if paths else np.zeros(0),
        np.array([agents[i].dims[0] / 2 for i in idx]), np.array([agents[i].dims[1] / 2 for i in idx]),
        v0, 1.0 + uu[:, 1], 1.5 + uu[:, 2], 1.0 + 0.8 * uu[:, 3],
        -cx * np.sin(pyaw) + cy * np.cos(pyaw), np.arctan2(np.sin(yaw - pyaw), np.cos(yaw - pyaw)),
        np.array([agents[i].category in RIDERS for i in idx], dtype=bool),
        stop_s, stop_sig, np.array([r[4] is not None for r in lane_rows], dtype=bool))
    walk_tracks = _walk_tracks(agents, walkers, walk_speed, city)
    first = MotionState(0, s0, np.zeros(len(idx)), np.zeros(len(idx), dtype=bool), walk_tracks[1],
                        walk_tracks[2], walk_tracks[0].speed.copy())
    motion = Motion(agents, lane_tracks, walk_tracks[0], plan_list, first)
    # Initial speeds: a fraction of v0, no more than the gap ahead allows at the track's headway.
    if len(idx):
        # Twice: the second pass sees where crossing tracks are going at the first pass's speeds.
        wanted = (0.6 + 0.4 * uu[:, 4]) * v0
        for _ in range(2):
            gap, _ = motion.lane_gaps(first, 0.0, motion.poses(first, 0.0))
            wanted = np.minimum(wanted, np.maximum(gap - S0, 0.0) / lane_tracks.headway)
            first.v = wanted
        motion.initial = _copy(first)
        motion._cursor = _copy(first)
    return motion


def _walk_tracks(agents: tuple[Agent, ...], walkers: list[int], speed: np.ndarray, city: City):
    """(WalkTracks, u0, d0): each walker's line along its strip (the road's way) or crosswalk."""
    strips = [(s.center, s.length, s.width, s.yaw, s.road_yaw) for s in city.sidewalks if s.kind == "sidewalk"]
    strips += [(c.center, c.length, c.width, c.yaw, c.yaw) for c in city.crosswalks]
    origin, axis, lo, hi, u0, d0, yaw0 = [], [], [], [], [], [], []
    for i in walkers:
        a = agents[i]
        strip = _strip_of(a, strips)
        center, length, width, syaw, walk_yaw = strip
        along_strip = abs(math.cos(walk_yaw - syaw)) > 0.7
        half = (length if along_strip else width) / 2
        ax = np.array([math.cos(walk_yaw), math.sin(walk_yaw)])
        rel = np.subtract(a.center[:2], center)
        u = float(rel @ ax)
        bound = max(half - a.dims[0] / 2 - 0.05, abs(u))
        d = 1.0 if math.cos(a.yaw - walk_yaw) >= 0 else -1.0
        origin.append(np.asarray(center, dtype=np.float64) + (rel - u * ax))
        axis.append(ax)
        lo.append(-bound)
        hi.append(bound)
        u0.append(u)
        d0.append(d)
        base = walk_yaw + (0.0 if d > 0 else math.pi)
        yaw0.append(math.atan2(math.sin(a.yaw - base), math.cos(a.yaw - base)))
    n = len(walkers)
    tracks = WalkTracks(np.array(walkers, dtype=np.int64), np.array(origin).reshape(n, 2), np.array(axis).reshape(n, 2),
                        np.array(lo), np.array(hi), np.asarray(speed, dtype=np.float64), np.array(yaw0))
    return tracks, np.array(u0, dtype=np.float64), np.array(d0, dtype=np.float64)


def _strip_of(agent: Agent, strips: list) -> tuple:
    """The sidewalk strip or crosswalk containing the agent's centre (the nearest centre if none:
    placement puts every walker inside one)."""
    best, best_d = None, math.inf
    for strip in strips:
        center, length, width, syaw, _ = strip
        rel = np.subtract(agent.center[:2], center)
        a, b = rel @ (math.cos(syaw), math.sin(syaw)), rel @ (-math.sin(syaw), math.cos(syaw))
        outside = max(abs(a) - length / 2, 0.0) + max(abs(b) - width / 2, 0.0)
        if outside < best_d:
            best, best_d = strip, outside
    return best


def posed_agents(motion: Motion, pose: Poses) -> tuple[tuple[Agent, ...], tuple[Vec3, ...]]:
    """The present agents at `pose` (moved ones re-posed, still ones as placed) and their velocities."""
    out, vel = [], []
    moving = np.zeros(len(motion.agents), dtype=bool)
    moving[motion.lane.index] = True
    moving[motion.walk.index] = True
    for i, a in enumerate(motion.agents):
        if not pose.present[i]:
            continue
        if moving[i]:
            a = replace(a, center=(float(pose.xy[i, 0]), float(pose.xy[i, 1]), a.center[2]), yaw=float(pose.yaw[i]))
        out.append(a)
        vel.append((float(pose.vel[i, 0]), float(pose.vel[i, 1]), 0.0))
    return tuple(out), tuple(vel)
