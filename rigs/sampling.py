"""Drawing one camera (pose and K) for a frame from a rig, the frame's generator and the scene.

World: x east, y north, z up, the road surface at z = 0 (scenes/). The camera is an OpenCV
camera, X_cam = R X_world + t, built from a heading (yaw, about +z from +x) and a pitch (below
the horizon, positive down), no roll:
    forward = (cos p cos y, cos p sin y, -sin p), right = (sin y, -cos y, 0), down = forward x right
R's rows are (right, down, forward). Pitch 90 degrees looks straight down, the heading then sets
which way is "up" in the image.

Placement (`placement_problem`): a pose is redrawn when the camera stands inside or within 0.5 m
of a building, an agent's cuboid or a furniture footprint (below its top; 1.5 m of a tree's crown
between the crown's base and the tree's top), when something taller than the camera stands
within 3 m in front of it, when a `traffic` or `lane` camera is not over a driving lane looking
along it (`lane_problem`: the anchors draw inside the lane, this holds them to it), or when more
of its image than the rig's `max_near_share` sees geometry nearer than its `near_distance`
(`view_problem`, rays against the render meshes: a pole camera looking into a signal arm). These
never give up before a pose passes them (PLACEMENT_TRIES past max_tries). Objects: a pose is
also redrawn when fewer than the rig's `min_objects` agents would be annotated by a cheap
geometric estimate (cuboid in front, in the image, at least MIN_BOX_PIXELS tall and wide, nearer
than MAX_DISTANCE); after max_tries the last placed pose is kept. The renderer checks the real
count after annotation and redraws again if the estimate was optimistic (buildings hide agents);
see rigs/render.py.

Randomness: only the generator passed in (the frame's rig stream, `rig_rng(seed, index)`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import shapely
from shapely.geometry import Point, Polygon

from omnigen.camera import Camera, frozen_array, intrinsics_from_fov
from omnigen.geometry import Box3D, Plane, cuboid_corners, project_boxes, rot_z
from omnigen.rigs.rig import Rig
from omnigen.scenes.description import Lane, Scene
from omnigen.scenes.seeding import choice_index

_RIG_SPAWN_KEY = (0x0416,)
MIN_BOX_PIXELS = 6.0
MAX_DISTANCE = 250.0
CLEARANCE = 0.5
WALL_AHEAD, WALL_WIDTH = 3.0, 1.2
"""A pose is redrawn when something taller than the camera stands within 3 m in front of it, in a
1.2 m wide corridor (the traffic anchor's leader is at least 4 m ahead)."""
CROWN_CLEARANCE = 1.5
"""Metres a camera keeps from a tree's crown (its cuboid's footprint) below the tree's top: a
camera closer sees a wall of leaves (the trunk's footprint alone let pole cameras stand in crowns)."""
TRAFFIC_GAP = (4.0, 30.0)
"""Metres from the `traffic` anchor's camera to the rear of the vehicle it follows: city
following distances, from queueing at a light to a couple of seconds at 50 km/h."""
FOLLOWED = ("car", "van", "truck", "bus")


def rig_rng(dataset_seed: int, frame_index: int) -> np.random.Generator:
    """The camera's own stream for frame `frame_index`: independent of the scene's streams
    (which come from default_rng([seed, index]) spawned), so changing the rig leaves agents,
    weather and lighting of a frame unchanged."""
    return np.random.default_rng(np.random.SeedSequence([int(dataset_seed), int(frame_index)], spawn_key=_RIG_SPAWN_KEY))


def camera_rotation(yaw: float, pitch: float) -> np.ndarray:
    """World-to-OpenCV-camera rotation for a heading `yaw` and a downward `pitch` (radians)."""
    cp, sp, cy, sy = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    f = np.array([cp * cy, cp * sy, -sp])
    r = np.array([sy, -cy, 0.0])
    d = np.cross(f, r)
    return np.stack([r, d, f])


@dataclass(frozen=True, eq=False)
class DrawnCamera(Camera):
    """One drawn camera: the core Camera (K; X_cam = R X_world + t; the image's size), which the
    renderers and the annotator take as it is, and how it was drawn: where it stands, its heading,
    pitch and field of view, its anchor and the draws it took. `position` is kept as drawn (t was
    made from it), so the record's ground plane and camera height are its exact numbers."""

    position: np.ndarray  # world
    yaw: float  # radians
    pitch: float  # radians, below the horizon
    hfov: float  # radians
    anchor: str
    tries: int = 1

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "position", frozen_array(self.position, (3,), "position"))

    @property
    def camera_height(self) -> float:
        return float(self.position[2])

    @property
    def ground_plane(self) -> Plane:
        """The world's z = 0 in this camera's frame: normal R e_z, offset = height above it."""
        return Plane(self.R @ np.array([0.0, 0.0, 1.0]), float(self.position[2]))

    def to_dict(self) -> dict:
        return {"position": [round(float(v), 6) for v in self.position], "yaw": round(self.yaw, 6),
                "pitch": round(self.pitch, 6), "hfov": round(self.hfov, 6), "anchor": self.anchor, "tries": self.tries}


def agent_box(agent, camera: Camera) -> Box3D:
    """An agent's cuboid in the camera's frame."""
    return Box3D(agent.center, agent.dims, rot_z(agent.yaw)).transformed(camera.R, camera.t)


def _weighted(rng: np.random.Generator, items: list, weights: list[float]):
    w = np.asarray(weights, dtype=np.float64)
    return items[int(rng.choice(len(items), p=w / w.sum()))]


def leaders(scene: Scene) -> list:
    """The moving vehicles a `traffic` camera may follow."""
    return [a for a in scene.agents if a.state == "moving" and a.category in FOLLOWED]


POLE_MOUNT = 0.9
"""Metres from a corner pole's axis to a camera mounted on it: outside the pole's obstacle
footprint grown by CLEARANCE, on the side facing the junction."""
CORNERS = ((1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0))


def corner_pole(city, inter, sx: float, sy: float):
    """The pole the layout stood on the (sx, sy) corner of `inter` (`furniture.corner_poles`), or None."""
    want = f"{inter.intersection_id}_pole{CORNERS.index((float(sx), float(sy)))}"
    return next((f for f in city.furniture if f.furniture_id == want), None)


@dataclass(frozen=True)
class _Lanes:
    """A city's driving lanes as arrays, so a point (or many) is located in all of them at once."""

    lanes: tuple[Lane, ...]
    start: np.ndarray  # (n, 2)
    along: np.ndarray  # (n, 2) unit vectors in the driving direction
    length: np.ndarray  # (n,)
    half_width: np.ndarray  # (n,)
    heading: np.ndarray  # (n,)

    @staticmethod
    def of(city) -> _Lanes:
        lanes = tuple(ln for r in city.roads for ln in r.lanes if ln.kind == "driving")
        start = np.array([ln.start for ln in lanes], dtype=np.float64).reshape(-1, 2)
        end = np.array([ln.end for ln in lanes], dtype=np.float64).reshape(-1, 2)
        length = np.array([ln.length for ln in lanes], dtype=np.float64)  # Lane.length's own float
        return _Lanes(lanes, start, (end - start) / np.maximum(length, 1e-12)[:, None], length,
                      np.array([ln.width / 2 for ln in lanes], dtype=np.float64), np.array([ln.heading for ln in lanes]))

    def coordinates(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(m, n) distance along each lane from its start and offset to its left, of m points."""
        rel = np.asarray(xy, dtype=np.float64).reshape(-1, 1, 2) - self.start[None]
        along = (rel * self.along[None]).sum(-1)
        across = rel[..., 1] * self.along[None, :, 0] - rel[..., 0] * self.along[None, :, 1]
        return along, across

    def under(self, xy: np.ndarray, yaw: np.ndarray, tolerance: float, side: float = 0.0, ends: float = 0.0) -> np.ndarray:
        """(m,) index of the first lane holding each point `side` metres in from its edges and
        `ends` in from its ends, heading within `tolerance` (radians) of its `yaw`; -1: none."""
        along, across = self.coordinates(xy)
        turn = np.abs(np.remainder(np.asarray(yaw, dtype=np.float64).reshape(-1, 1) - self.heading[None] + math.pi,
                                   2 * math.pi) - math.pi)
        inside = ((along >= ends - 1e-9) & (along <= self.length[None] - ends + 1e-9)
                  & (np.abs(across) <= self.half_width[None] - side + 1e-9) & (turn <= tolerance + 1e-9))
        return np.where(inside.any(axis=1), inside.argmax(axis=1), -1)


def driving_lanes(city) -> _Lanes:
    """The city's driving lanes as arrays (once per city)."""
    return _per_city(city, "lanes", _Lanes.of)


EGO_HALF_WIDTH = 0.9
"""Metres from a `traffic` or `lane` camera to its lane's side edges at least: half a car's width,
so the car that carries the camera stands inside its lane, not over the kerb."""
EGO_LANE_END = 3.0
"""Metres from a lane camera to its lane's ends at least (lanes run from city bound to bound:
the car behind the camera stays on the road)."""
LATERAL_SD = 0.2
"""Metres: the spread of a lane camera across its lane (clipped to the lane less EGO_HALF_WIDTH)."""
LEADER_TURN = math.radians(10.0)
"""How far a followed vehicle's heading may turn from its lane's (placement draws at most 6 degrees)."""


def lane_problem(rig: Rig, city, cam: DrawnCamera) -> str | None:
    """Why a `traffic` or `lane` camera does not stand over a driving lane, looking along it (its
    car within the lane, EGO_HALF_WIDTH from the lane's edges, EGO_LANE_END from its ends; its
    heading within the rig's yaw_jitter of the lane's), or None; other anchors have no lane."""
    if cam.anchor not in ("traffic", "lane"):
        return None
    turn = math.radians(max(abs(rig.yaw_jitter[0]), abs(rig.yaw_jitter[1])))
    if driving_lanes(city).under(cam.position[:2], cam.yaw, turn, EGO_HALF_WIDTH, EGO_LANE_END)[0] < 0:
        return "not over a driving lane, looking along it"
    return None


def _in_lane(lanes: _Lanes, k: int, along: float, across: float, rng: np.random.Generator) -> np.ndarray:
    """The point `along` lane k and `across` plus the lateral spread, kept EGO_HALF_WIDTH in."""
    room = max(float(lanes.half_width[k]) - EGO_HALF_WIDTH, 0.0)
    across = min(max(across + float(rng.normal(0.0, LATERAL_SD)), -room), room)
    d = lanes.along[k]
    return lanes.start[k] + along * d + across * np.array([-d[1], d[0]])


def _behind_leader(scene: Scene, rng: np.random.Generator) -> tuple[np.ndarray, float] | None:
    """A camera 4-30 m behind one of the frame's moving vehicles, in the same lane, looking along
    it; None when no vehicle has room behind it in its lane (a camera further back stood past the
    lane's start, off the city, or off the lane where the leader's heading turns from it).

    The leader is drawn among those with at least TRAFFIC_GAP[0] of lane behind them, the gap up
    to what the lane leaves, so every draw lands in the leader's lane."""
    lead = leaders(scene)
    if not lead:
        return None
    lanes = driving_lanes(scene.city)
    centers = np.array([a.center[:2] for a in lead], dtype=np.float64)
    k = lanes.under(centers, np.array([a.yaw for a in lead]), LEADER_TURN)
    along, across = lanes.coordinates(centers)
    rows = np.arange(len(lead))
    behind = along[rows, k] - np.array([a.dims[0] / 2 for a in lead]) - EGO_LANE_END
    room = np.where(k >= 0, behind, -math.inf)
    ok = np.nonzero(room >= TRAFFIC_GAP[0])[0]
    if not len(ok):
        return None
    i = int(ok[int(rng.integers(len(ok)))])
    gap = rng.uniform(TRAFFIC_GAP[0], min(TRAFFIC_GAP[1], float(room[i])))
    lane = int(k[i])
    p = _in_lane(lanes, lane, float(along[i, lane]) - lead[i].dims[0] / 2 - gap, float(across[i, lane]), rng)
    return p, float(lanes.heading[lane])


def _anchor_pose(rig: Rig, anchor: str, scene: Scene, rng: np.random.Generator,
                 junction=None) -> tuple[np.ndarray, float, str]:
    """(x, y), a base heading and the anchor kind used: `traffic` without a moving vehicle to
    follow in the frame falls back to `lane` (a camera in an empty lane), and the record then says so.
    `junction`: the intersection an `intersection` camera stands at (several rigs meeting at one,
    rigs/meeting.py), else drawn."""
    city = scene.city
    if anchor == "traffic":
        follow = _behind_leader(scene, rng)
        if follow is not None:
            return follow[0], follow[1], anchor
        anchor = "lane"
    if anchor == "lane":
        lanes = driving_lanes(city)
        k = choice_index(rng, lanes.length / lanes.length.sum())
        p = _in_lane(lanes, k, rng.uniform(0.05, 0.95) * float(lanes.length[k]), 0.0, rng)
        return p, float(lanes.heading[k]), anchor
    if anchor == "intersection":
        inter = junction if junction is not None else city.intersections[int(rng.integers(len(city.intersections)))]
        sx, sy = rng.choice([-1.0, 1.0], size=2)
        off = rng.uniform(1.0, 3.0, size=2)
        c = np.asarray(inter.center)
        p = c + np.array([sx * (inter.size[0] / 2 + off[0]), sy * (inter.size[1] / 2 + off[1])])
        pole = corner_pole(city, inter, sx, sy)
        if pole is not None:  # mounted on the corner's pole, on the junction side (as DAIR's cameras)
            q = np.mean(np.asarray(pole.footprint), axis=0)  # the pole's axis (its centre is the arm's cuboid's)
            p = q + POLE_MOUNT * (c - q) / np.linalg.norm(c - q)
        return p, math.atan2(c[1] - p[1], c[0] - p[0]), anchor
    if anchor == "roadside":
        road = _weighted(rng, list(city.roads), [math.dist(r.start, r.end) for r in city.roads])
        length = math.dist(road.start, road.end)
        d = np.subtract(road.end, road.start) / length
        n = np.array([-d[1], d[0]])
        side = rng.choice([-1.0, 1.0])
        p = np.asarray(road.start) + rng.uniform(0.1, 0.9) * length * d + side * n * (road.width / 2 + rng.uniform(0.5, 2.0))
        along = d if rng.random() < 0.5 else -d
        base = math.atan2(along[1], along[0])
        # turn in towards the road: the road lies on the -side of the normal from the camera
        inward = -side * n
        turn = math.radians(rng.uniform(10.0, 40.0))
        cross = along[0] * inward[1] - along[1] * inward[0]
        return p, base + math.copysign(turn, cross), anchor
    xmin, ymin, xmax, ymax = city.bounds
    mx, my = 0.1 * (xmax - xmin), 0.1 * (ymax - ymin)
    return np.array([rng.uniform(xmin + mx, xmax - mx), rng.uniform(ymin + my, ymax - my)]), 0.0, anchor


@dataclass(frozen=True)
class _Layer:
    """Obstacles (shapely polygons, with the heights between which each one blocks) in an STRtree."""

    polys: np.ndarray
    tops: np.ndarray
    bottoms: np.ndarray
    tree: shapely.STRtree

    @staticmethod
    def of(polys: list, tops: list[float], bottoms: list[float]) -> _Layer:
        arr = np.asarray(polys, dtype=object)
        return _Layer(arr, np.asarray(tops, dtype=np.float64).reshape(-1), np.asarray(bottoms, dtype=np.float64).reshape(-1),
                      shapely.STRtree(arr))


_CITY_CACHE: dict[int, tuple[object, dict[str, object]]] = {}  # id(city) -> (city, what was built from it)
_CITY_CACHE_SIZE = 4


def _per_city(city, key: str, build):
    """`build(city)`, made once per city object and kept for its later frames: a fixed city's
    obstacles, lanes and triangles are the same in every frame, only its agents change. The
    entry holds the city, so an id is never taken for another city's."""
    hit = _CITY_CACHE.get(id(city))
    if hit is None or hit[0] is not city:
        _CITY_CACHE.pop(id(city), None)
        while len(_CITY_CACHE) >= _CITY_CACHE_SIZE:
            _CITY_CACHE.pop(next(iter(_CITY_CACHE)))
        hit = _CITY_CACHE[id(city)] = (city, {})
    made = hit[1]
    if key not in made:
        made[key] = build(city)
    return made[key]


def _city_layer(city) -> _Layer:
    """The static city's obstacles (buildings, furniture, tree crowns), once per city."""
    return _per_city(city, "layer", _build_city_layer)


def _build_city_layer(city) -> _Layer:
    polys, tops, bottoms = [], [], []
    for b in city.buildings:
        for part in b.parts:
            polys.append(Polygon(part.footprint))
            tops.append(part.top_z + part.roof_height)
            bottoms.append(-math.inf)
    for f in city.furniture:
        top = f.center[2] + f.dims[2] / 2
        polys.append(Polygon(f.footprint) if len(f.footprint) >= 3 else Point(f.center[:2]).buffer(0.2))
        tops.append(top)
        bottoms.append(-math.inf)
        if f.kind == "tree":  # and its crown: a camera in or just beside it sees a wall of leaves
            crown = shapely.box(f.center[0] - f.dims[0] / 2, f.center[1] - f.dims[1] / 2,
                                f.center[0] + f.dims[0] / 2, f.center[1] + f.dims[1] / 2)
            polys.append(crown.buffer(CROWN_CLEARANCE - CLEARANCE))
            tops.append(top)
            # below the crown (a dashcam under a street tree) the view is open
            bottoms.append(f.center[2] - f.dims[2] / 2 + float(f.params.get("clearance", 0.0)) - CLEARANCE)
    return _Layer.of(polys, tops, bottoms)


def _agent_layer(agents) -> _Layer:
    """The agents' footprints: each cuboid's base, turned by its yaw, as one array operation.

    The same polygons as shapely.affinity.affine_transform(shapely.box(-l/2, -w/2, l/2, w/2),
    [c, -s, s, c, x, y]) per agent: the box's ring (shapely.box's vertex order) and that function's
    own arithmetic (x' = c x - s y + x0, y' = s x + c y + y0, elementwise), for all agents at once."""
    if not agents:
        return _Layer.of([], [], [])
    dims = np.array([a.dims for a in agents], dtype=np.float64)
    yaw = [a.yaw for a in agents]
    cos = np.array([math.cos(t) for t in yaw])[:, None]
    sin = np.array([math.sin(t) for t in yaw])[:, None]
    x0 = np.array([a.center[0] for a in agents])[:, None]
    y0 = np.array([a.center[1] for a in agents])[:, None]
    lx, hx = -dims[:, 0:1] / 2, dims[:, 0:1] / 2
    ly, hy = -dims[:, 1:2] / 2, dims[:, 1:2] / 2
    x = np.hstack([hx, hx, lx, lx, hx])  # shapely.box(xmin, ymin, xmax, ymax): counter-clockwise from (xmax, ymin)
    y = np.hstack([ly, hy, hy, ly, ly])
    xp = cos * x + (-sin) * y + x0
    yp = sin * x + cos * y + y0
    polys = shapely.polygons(np.stack([xp, yp], axis=-1))
    tops = [a.center[2] + a.dims[2] / 2 for a in agents]
    return _Layer.of(polys, tops, [-math.inf] * len(agents))


class Obstacles:
    """What a camera may not stand in: buildings, agents' cuboids, furniture; built per scene.

    Two layers, each with its STRtree: the static city's (shared by every frame of the city) and
    this frame's agents'. A pose is blocked when anything in either layer blocks it. `skip`: ids
    of agents that are no obstacle (the car an ego camera rides on, rigs/meeting.py)."""

    def __init__(self, scene: Scene, skip: frozenset[int] = frozenset()) -> None:
        agents = [a for a in scene.agents if a.instance_id not in skip] if skip else scene.agents
        self.layers = (_city_layer(scene.city), _agent_layer(agents))

    def blocked(self, position: np.ndarray) -> bool:
        pt = Point(position[:2])
        z = position[2]
        for layer in self.layers:
            idx = layer.tree.query(pt, predicate="dwithin", distance=CLEARANCE)
            if ((layer.tops[idx] + CLEARANCE > z) & (layer.bottoms[idx] < z)).any():
                return True
        return False

    def wall_ahead(self, position: np.ndarray, yaw: float) -> bool:
        """True when something taller than the camera stands within WALL_AHEAD metres in front
        of it (a corridor WALL_WIDTH wide): a dashcam right behind a queued bus sees only its back."""
        d = np.array([math.cos(yaw), math.sin(yaw)])
        corridor = shapely.box(0.0, -WALL_WIDTH / 2, WALL_AHEAD, WALL_WIDTH / 2)
        corridor = shapely.affinity.affine_transform(corridor, [d[0], -d[1], d[1], d[0], position[0], position[1]])
        z = position[2]
        for layer in self.layers:
            idx = layer.tree.query(corridor, predicate="intersects")
            if ((layer.tops[idx] > z) & (layer.bottoms[idx] < z)).any():
                return True
        return False


NEAR_GRID = 64
"""Rays across the image's width that `near_share` casts (rows in proportion): a 64 x 48 grid at
4:3, each ray 1/3072 of the image, fine enough to measure a 2% limit."""


@dataclass(frozen=True)
class _Triangles:
    """World triangles with their bounding boxes, to keep those near a camera by one array test."""

    corners: np.ndarray  # (m, 3, 3)
    lo: np.ndarray  # (m, 3)
    hi: np.ndarray  # (m, 3)

    @staticmethod
    def of(meshes: list[tuple[dict, np.ndarray]]) -> _Triangles:
        """The triangles of (parts, object-to-world 4x4) pairs, as the renderers place them."""
        tris = [np.zeros((0, 3, 3))]
        for parts, matrix in meshes:
            for m in parts.values():
                v = np.asarray(m.vertices, dtype=np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
                tris.append(v[np.asarray(m.faces, dtype=np.int64)])
        corners = np.concatenate(tris)
        return _Triangles(corners, corners.min(axis=1), corners.max(axis=1))

    def near(self, point: np.ndarray, within: float) -> np.ndarray:
        """(k, 3, 3) the triangles whose bounding box comes within `within` metres of `point`."""
        gap = np.maximum(np.maximum(self.lo - point, point - self.hi), 0.0)
        return self.corners[(gap * gap).sum(axis=1) <= within * within]


def _static_triangles(city) -> _Triangles:
    """The city's render geometry (ground, markings, buildings, furniture: scenes/meshes.py's, which
    both backends draw), once per city."""
    from omnigen.scenes.meshes import static_objects

    return _per_city(city, "triangles", lambda c: _Triangles.of([(o.parts, o.matrix_world) for o in static_objects(c)]))


def _near_agent_triangles(scene: Scene, point: np.ndarray, within: float) -> np.ndarray:
    """The triangles of the agents near `point`, as `_Triangles.near` keeps them (an agent's mesh
    is fitted to its cuboid, so no part of it lies further than half its diagonal from its centre)."""
    from omnigen.scenes.assets.build import agent_parts
    from omnigen.scenes.meshes import pose_matrix

    near = [a for a in scene.agents
            if math.dist(a.center, point) <= within + 0.5 * math.hypot(*a.dims)]
    if not near:
        return np.zeros((0, 3, 3))
    return _Triangles.of([(agent_parts(a.asset, a.dims)[0], pose_matrix(a.center, a.yaw)) for a in near]).near(point, within)


def _hits_within(origin: np.ndarray, dirs: np.ndarray, tris: np.ndarray, t_max: float, chunk: int = 1 << 20) -> np.ndarray:
    """(n,) whether each ray origin + t dirs meets any triangle at 0 < t < t_max (Moller-Trumbore,
    all rays against all triangles, in chunks of about `chunk` pairs)."""
    hit = np.zeros(len(dirs), dtype=bool)
    step = max(1, chunk // max(len(dirs), 1))
    for s in range(0, len(tris), step):
        t = tris[s:s + step]
        e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]  # (k, 3)
        pv = np.cross(dirs[:, None, :], e2[None])  # (n, k, 3)
        det = (pv * e1[None]).sum(-1)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = origin - t[:, 0]  # (k, 3)
        u = (pv * tv[None]).sum(-1) * inv
        qv = np.cross(tv, e1)  # (k, 3)
        v = (dirs @ qv.T) * inv
        dist = (qv * e2).sum(-1)[None] * inv
        hit |= (ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (dist > 0) & (dist < t_max)).any(axis=1)
    return hit


def _in_view(tris: np.ndarray, cam: Camera, rays: np.ndarray, within: float) -> np.ndarray:
    """The triangles not wholly outside one side of the pyramid the camera-frame `rays` (z = 1)
    span between depth 0 and `within`: only those can meet a ray there."""
    c = tris @ cam.R.T + cam.t  # (k, 3, 3) camera frame
    x, y, z = c[..., 0], c[..., 1], c[..., 2]
    lo, hi = rays.min(axis=0), rays.max(axis=0)
    out = ((z <= 0).all(1) | (z >= within).all(1) | (x < lo[0] * z).all(1) | (x > hi[0] * z).all(1)
           | (y < lo[1] * z).all(1) | (y > hi[1] * z).all(1))
    return tris[~out]


def near_share(scene: Scene, cam: Camera, within: float, grid: int = NEAR_GRID) -> float:
    """The share of the image that sees geometry nearer than `within` metres (camera depth, as in
    the depth EXR): rays through a `grid`-wide lattice of pixel centres against the render meshes
    of the city and the agents near the camera. A pole camera's own pole, a signal arm or a crown
    beside it fills the image's edge with a blur the detector cannot use."""
    gw = max(2, int(grid))
    gh = max(2, int(round(gw * cam.height / cam.width)))
    u = (np.arange(gw) + 0.5) * cam.width / gw - 0.5
    v = (np.arange(gh) + 0.5) * cam.height / gh - 0.5
    uu, vv = np.meshgrid(u, v)
    rays = np.linalg.solve(cam.K, np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])).T  # camera frame, z = 1
    dirs = rays @ cam.R  # in the world: a hit's ray parameter is its camera depth
    origin = -cam.R.T @ cam.t
    # a point nearer than `within` in depth lies at most `within` times the longest ray's length away
    reach = within * float(np.linalg.norm(rays, axis=1).max())
    tris = np.concatenate([_static_triangles(scene.city).near(origin, reach), _near_agent_triangles(scene, origin, reach)])
    tris = _in_view(tris, cam, rays, within)
    if not len(tris):
        return 0.0
    return float(_hits_within(origin, dirs, tris, within).mean())


def view_problem(rig: Rig, scene: Scene, cam: Camera) -> str | None:
    """Why a camera's view is blocked close by (more than the rig's max_near_share of the image
    nearer than its near_distance), or None; rigs without a near_distance are not checked."""
    if rig.near_distance <= 0:
        return None
    share = near_share(scene, cam, rig.near_distance)
    if share > rig.max_near_share:
        return f"{share:.1%} of the image within {rig.near_distance:g} m"
    return None


def projected_agents(scene: Scene, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(N,) camera depth of each agent's centre and (N, 4) its projected cuboid's box (NaN rows
    where nothing is in the image): project_box over all agents at once (project_boxes), since
    drawing a pose tests a few hundred agents tens of times."""
    if not scene.agents:
        return np.zeros(0), np.zeros((0, 4))
    centers = np.array([a.center for a in scene.agents], dtype=np.float64)
    dims = np.array([a.dims for a in scene.agents], dtype=np.float64)
    rot = np.stack([cam.R @ rot_z(a.yaw) for a in scene.agents])
    cam_centers = cam.to_camera(centers)
    proj = project_boxes(cuboid_corners(cam_centers, dims, rot), cam.K, cam.width, cam.height)
    return cam_centers[:, 2], proj.bbox


def expected_objects(scene: Scene, cam: Camera) -> int:
    """Agents a camera would annotate by geometry alone (no occlusion): a quick pre-render check."""
    depth, bbox = projected_agents(scene, cam)
    near = (depth > 0.5) & (depth < MAX_DISTANCE) & ~np.isnan(bbox[:, 0])
    side = np.minimum(bbox[:, 2] - bbox[:, 0], bbox[:, 3] - bbox[:, 1])
    return int((near & (np.nan_to_num(side, nan=0.0) >= MIN_BOX_PIXELS)).sum())


def draw_camera(rig: Rig, scene: Scene, rng: np.random.Generator, width: int, height: int) -> DrawnCamera:
    """One candidate camera from the rig's distribution (no rejection)."""
    kinds = list(rig.anchor)
    anchor = _weighted(rng, kinds, [rig.anchor[k] for k in kinds])
    xy, heading, anchor = _anchor_pose(rig, anchor, scene, rng)
    return camera_at(rig, xy, heading, anchor, rng, width, height)


def camera_at(rig: Rig, xy: np.ndarray, heading: float, anchor: str, rng: np.random.Generator, width: int,
              height: int) -> DrawnCamera:
    """A camera standing at `xy` facing `heading`: height, yaw jitter, pitch and field of view
    drawn from the rig's ranges, in that order (every anchor's draws end so)."""
    z = rng.uniform(*rig.height)
    yaw = heading + math.radians(rng.uniform(*rig.yaw_jitter))
    pitch = math.radians(rng.uniform(*rig.pitch))
    hfov = math.radians(rng.uniform(*rig.hfov))
    return make_camera(xy, z, yaw, pitch, hfov, anchor, width, height)


def make_camera(xy, z: float, yaw: float, pitch: float, hfov: float, anchor: str, width: int,
                height: int) -> DrawnCamera:
    """The camera of a pose already drawn (radians; `xy` on the ground, `z` above it)."""
    R = camera_rotation(yaw, pitch)
    pos = np.array([xy[0], xy[1], z])
    K = intrinsics_from_fov(hfov, width, height)
    return DrawnCamera(K, R, -R @ pos, width, height, pos, math.atan2(math.sin(yaw), math.cos(yaw)), pitch, hfov, anchor)


PLACEMENT_TRIES = 240
"""Draws after rig.max_tries that a frame may still take while none of its poses passed the
placement checks (`placement_problem`): the object count may give up, where the camera stands
may not (a pole camera looking into its own arm is no frame)."""


def placement_problem(rig: Rig, scene: Scene, cam: DrawnCamera, obstacles: Obstacles) -> str | None:
    """Why a pose may not be kept whatever it sees, or None: it stands in or at an obstacle, a
    wall stands right in front of it, a `traffic` or `lane` camera is not over a driving lane
    looking along it (`lane_problem`), or too much of the view lies close by (`view_problem`).
    The cheap tests first: the view's rays only for poses that pass the rest."""
    if obstacles.blocked(cam.position):
        return "inside or at an obstacle"
    if obstacles.wall_ahead(cam.position, cam.yaw):
        return "a wall right ahead"
    return lane_problem(rig, scene.city, cam) or view_problem(rig, scene, cam)


def sample_camera(rig: Rig, scene: Scene, rng: np.random.Generator, width: int, height: int,
                  obstacles: Obstacles | None = None, start_try: int = 0, propose=None) -> DrawnCamera:
    """Draw until a pose passes the placement checks and expects at least rig.min_objects objects.

    After rig.max_tries the last pose that passed the placement checks is returned; while there
    is none, up to PLACEMENT_TRIES more draws look for one (then the first pose drawn is kept).
    `tries` says how many draws it took, counting from `start_try` (the renderer continues the
    count when it redraws). `propose(rig, scene, rng, width, height)` draws each candidate
    (default draw_camera: the rig's anchors; rigs/meeting.py: views aimed at one junction).
    """
    obstacles = obstacles or Obstacles(scene)
    propose = propose or draw_camera
    placed = first = None
    tries = start_try
    while tries < rig.max_tries or (placed is None and tries < rig.max_tries + PLACEMENT_TRIES):
        tries += 1
        cam = replace(propose(rig, scene, rng, width, height), tries=tries)
        first = first or cam
        if placement_problem(rig, scene, cam, obstacles):
            continue
        placed = cam
        if expected_objects(scene, cam) >= rig.min_objects:
            return cam
    return replace(placed or first or propose(rig, scene, rng, width, height), tries=tries)
