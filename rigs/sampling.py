"""Drawing one camera (pose and K) for a frame from a rig, the frame's generator and the scene.

World: x east, y north, z up, the road surface at z = 0 (scenes/). The camera is an OpenCV
camera, X_cam = R X_world + t, built from a heading (yaw, about +z from +x) and a pitch (below
the horizon, positive down), no roll:
    forward = (cos p cos y, cos p sin y, -sin p), right = (sin y, -cos y, 0), down = forward x right
R's rows are (right, down, forward). Pitch 90 degrees looks straight down, the heading then sets
which way is "up" in the image.

Rejection (`pose_problem`): a pose is redrawn when the camera stands inside or within 0.5 m of
a building, an agent's cuboid or a furniture footprint (below its top; 1.5 m of a tree's crown
between the crown's base and the tree's top), when something taller than the camera stands
within 3 m in front of it, or when fewer than the
rig's `min_objects` agents would be annotated by a cheap geometric estimate (cuboid in front, in
the image, at least MIN_BOX_PIXELS tall and wide, nearer than MAX_DISTANCE). The renderer checks
the real count after annotation and redraws again if the estimate was optimistic (buildings hide
agents); see rigs/render.py.

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
from omnigen.scenes.description import Scene

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


def _anchor_pose(rig: Rig, anchor: str, scene: Scene, rng: np.random.Generator) -> tuple[np.ndarray, float, str]:
    """(x, y), a base heading and the anchor kind used: `traffic` without moving vehicles in the
    frame falls back to `lane` (a camera in an empty lane), and the record then says so."""
    city = scene.city
    if anchor == "traffic":
        lead = leaders(scene)
        if lead:
            a = lead[int(rng.integers(len(lead)))]
            d = np.array([math.cos(a.yaw), math.sin(a.yaw)])
            back = a.dims[0] / 2 + rng.uniform(*TRAFFIC_GAP)
            p = np.asarray(a.center[:2]) - back * d + np.array([-d[1], d[0]]) * rng.normal(0.0, 0.2)
            return p, a.yaw, anchor
        anchor = "lane"
    if anchor == "lane":
        lanes = [ln for r in city.roads for ln in r.lanes if ln.kind == "driving"]
        lane = _weighted(rng, lanes, [ln.length for ln in lanes])
        s = rng.uniform(0.05, 0.95)
        d = np.subtract(lane.end, lane.start) / lane.length
        p = np.asarray(lane.start) + s * lane.length * d + np.array([-d[1], d[0]]) * rng.normal(0.0, 0.2)
        return p, lane.heading, anchor
    if anchor == "intersection":
        inter = city.intersections[int(rng.integers(len(city.intersections)))]
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


_CITY_LAYERS: dict[int, tuple[object, _Layer]] = {}  # id(city) -> (city, its layer); the city held, so ids stay unique
_CITY_LAYERS_SIZE = 4


def _city_layer(city) -> _Layer:
    """The static city's obstacles (buildings, furniture, tree crowns): built once per city, since
    every frame of a fixed city has the same ones and only its agents change."""
    hit = _CITY_LAYERS.get(id(city))
    if hit is not None and hit[0] is city:
        return hit[1]
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
    layer = _Layer.of(polys, tops, bottoms)
    _CITY_LAYERS.pop(id(city), None)
    while len(_CITY_LAYERS) >= _CITY_LAYERS_SIZE:
        _CITY_LAYERS.pop(next(iter(_CITY_LAYERS)))
    _CITY_LAYERS[id(city)] = (city, layer)
    return layer


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
    this frame's agents'. A pose is blocked when anything in either layer blocks it."""

    def __init__(self, scene: Scene) -> None:
        self.layers = (_city_layer(scene.city), _agent_layer(scene.agents))

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
    z = rng.uniform(*rig.height)
    yaw = heading + math.radians(rng.uniform(*rig.yaw_jitter))
    pitch = math.radians(rng.uniform(*rig.pitch))
    hfov = math.radians(rng.uniform(*rig.hfov))
    R = camera_rotation(yaw, pitch)
    pos = np.array([xy[0], xy[1], z])
    K = intrinsics_from_fov(hfov, width, height)
    return DrawnCamera(K, R, -R @ pos, width, height, pos, math.atan2(math.sin(yaw), math.cos(yaw)), pitch, hfov, anchor)


def sample_camera(rig: Rig, scene: Scene, rng: np.random.Generator, width: int, height: int,
                  obstacles: Obstacles | None = None, start_try: int = 0) -> DrawnCamera:
    """Draw until a pose is clear of geometry and expects at least rig.min_objects objects.

    After rig.max_tries the last clear pose (or the last one) is returned; `tries` says how many
    draws it took, counting from `start_try` (the renderer continues the count when it redraws).
    """
    obstacles = obstacles or Obstacles(scene)
    fallback = None
    tries = start_try
    while tries < rig.max_tries:
        tries += 1
        cam = draw_camera(rig, scene, rng, width, height)
        if obstacles.blocked(cam.position) or obstacles.wall_ahead(cam.position, cam.yaw):
            fallback = fallback or cam
            continue
        cam = replace(cam, tries=tries)
        fallback = cam
        if expected_objects(scene, cam) >= rig.min_objects:
            return cam
    if fallback is None:
        fallback = draw_camera(rig, scene, rng, width, height)
    return replace(fallback, tries=tries)
