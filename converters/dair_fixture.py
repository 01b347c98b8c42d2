"""Complete DAIR-V2X infrastructure-side frames, generated, for tests and benchmarks.

Only one real DAIR-V2X label file is public without registration, and no image or calibration for
it, so the converter is tested on frames built here: a pitched pole camera (6-10 m up, 10-25
degrees down, some yaw and a little roll) above flat ground, objects standing on that ground in
front of it, and every file in the official layout (image/, calib/camera_intrinsic/,
calib/virtuallidar_to_camera/, label/camera/, label/virtuallidar/, data_info.json; DAIR-V2X-C adds
calib/virtuallidar_to_world/ and batch fields). The files carry the real quirks: label numbers
sometimes as strings, class names in mixed case (`Trafficcone`), ignore classes.

Each frame draws from its own generator, np.random.default_rng([seed, index]), so frame i is the
same whatever n_frames is, and a tree is a pure function of its arguments.

The 2D boxes written into the labels are computed here with a plain pinhole projection of the
eight corners, clipped to the image, independently of omnigen.geometry.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

CLASS_SIZES: dict[str, tuple[float, float, float]] = {
    # DAIR-V2X class name: typical (l, w, h) in metres
    "Car": (4.5, 1.85, 1.5),
    "Van": (5.0, 2.0, 2.1),
    "Truck": (9.0, 2.6, 3.3),
    "Bus": (11.0, 2.8, 3.2),
    "Pedestrian": (0.6, 0.6, 1.7),
    "Cyclist": (1.8, 0.7, 1.6),
    "Motorcyclist": (1.9, 0.8, 1.6),
    "Tricyclist": (2.8, 1.3, 1.8),
    "Barrowlist": (1.3, 0.7, 1.1),
    "TrafficCone": (0.35, 0.35, 0.6),
}
CLASS_WEIGHTS = np.array([10, 2, 1, 1, 4, 2, 2, 1, 0.5, 2], dtype=np.float64)
IGNORE_NAMES = ("Unknown", "ignore")
"""Names outside the DAIR class list; the converter turns them into ignore regions."""
IGNORE_PROBABILITY = 0.06
LOCATIONS = ("yizhuang06", "yizhuang09", "yizhuang10")
T0_US = 1_626_155_000_000_000  # microseconds, DAIR-V2X's epoch (July 2021)

I_RUN = 7
"""DAIR-V2X-I fixture: runs of 7 frames 1 s apart, runs 5 minutes apart (so time grouping finds them)."""
C_BATCH = 10
"""DAIR-V2X-C fixture: batches of 10 frames 0.1 s apart, batches 10 minutes apart."""

VARIANTS = ("i", "c")
KEY_STYLES = ("std", "readme")
EXTRINSIC_STYLES = ("rt", "tr", "mixed")

LEVEL_CAMERA_TO_LIDAR = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Columns: the camera's x (right), y (down), z (forward) in the virtual-LiDAR frame (x forward,
y left, z up) for a level camera looking along +x."""


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class FixtureCamera:
    """The truth behind one frame's calibration files."""

    K: np.ndarray
    rotation: np.ndarray  # virtual LiDAR -> camera
    translation: np.ndarray
    height: float  # camera centre above the ground, metres
    pitch: float  # optical axis below the horizon, radians
    ground_z: float  # the ground's z in the virtual-LiDAR frame

    @property
    def center(self) -> np.ndarray:
        return -self.rotation.T @ self.translation


@dataclass(frozen=True)
class DairFixture:
    root: Path  # the infrastructure-side folder (holds data_info.json)
    variant: str
    keys: list[str]  # DAIR frame ids, "000000", ...
    cameras: list[FixtureCamera]


def make_camera(rng: np.random.Generator, image_size: tuple[int, int]) -> FixtureCamera:
    """A pole camera 6-10 m up, pitched 10-25 degrees down, yawed up to 30 degrees, rolled up to 1.5."""
    width, height_px = image_size
    height = rng.uniform(6.0, 10.0)
    pitch = math.radians(rng.uniform(10.0, 25.0))
    yaw = math.radians(rng.uniform(-30.0, 30.0))
    roll = math.radians(rng.uniform(-1.5, 1.5))
    ground_z = rng.uniform(-2.0, 0.0)
    position = np.array([rng.uniform(-5.0, 5.0), rng.uniform(-5.0, 5.0), ground_z + height])
    f = (width / 2.0) / math.tan(math.radians(rng.uniform(45.0, 60.0)) / 2.0)
    K = np.array([[f * rng.uniform(0.998, 1.002), 0.0, width / 2.0 - 0.5 + rng.uniform(-1, 1)],
                  [0.0, f, height_px / 2.0 - 0.5 + rng.uniform(-1, 1)],
                  [0.0, 0.0, 1.0]])
    camera_to_lidar = _rot_z(yaw) @ LEVEL_CAMERA_TO_LIDAR @ _rot_x(-pitch) @ _rot_z(roll)
    rotation = camera_to_lidar.T
    return FixtureCamera(K, rotation, -rotation @ position, height, pitch, ground_z)


def box_corners_lidar(center: np.ndarray, lwh: np.ndarray, yaw: float) -> np.ndarray:
    """(8, 3) corners in the contract's order (0-3 top, 4-7 bottom; front = +l/2, left = +w/2)."""
    signs = np.array([[1, 1, 1], [1, -1, 1], [-1, -1, 1], [-1, 1, 1],
                      [1, 1, -1], [1, -1, -1], [-1, -1, -1], [-1, 1, -1]], dtype=np.float64)
    return (signs * np.asarray(lwh) / 2.0) @ _rot_z(yaw).T + np.asarray(center)


def _box2d(cam: FixtureCamera, corners_lidar: np.ndarray, image_size: tuple[int, int]) -> tuple[list[float], bool] | None:
    """Pinhole projection of the corners, clipped to the image; None if not wholly in front or not in view."""
    pts = corners_lidar @ cam.rotation.T + cam.translation
    if pts[:, 2].min() < 1.0:
        return None
    uv = pts @ cam.K.T
    uv = uv[:, :2] / uv[:, 2:3]
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    w, h = image_size
    x1, y1 = max(lo[0], -0.5), max(lo[1], -0.5)
    x2, y2 = min(hi[0], w - 0.5), min(hi[1], h - 0.5)
    if x2 - x1 < 1.0 or y2 - y1 < 1.0:
        return None
    truncated = bool(lo[0] < -0.5 or lo[1] < -0.5 or hi[0] > w - 0.5 or hi[1] > h - 0.5)
    return [float(x1), float(y1), float(x2), float(y2)], truncated


def _ground_point(rng: np.random.Generator, cam: FixtureCamera, image_size: tuple[int, int]) -> np.ndarray | None:
    """Where the ray through a random pixel (lower image, a little beyond the sides) meets the ground."""
    w, h = image_size
    pixel = np.array([rng.uniform(-0.15 * w, 1.15 * w), rng.uniform(0.35 * h, 1.1 * h), 1.0])
    ray = cam.rotation.T @ np.linalg.solve(cam.K, pixel)
    if ray[2] > -1e-3:
        return None
    origin = cam.center
    point = origin + (cam.ground_z - origin[2]) / ray[2] * ray
    return point if np.hypot(*(point - origin)[:2]) < 120.0 else None


def _name_variant(rng: np.random.Generator, name: str) -> str:
    """DAIR-V2X writes class names in several cases; `Trafficcone` is the real one."""
    return (name, name.lower(), name.upper(), name.capitalize())[int(rng.integers(4))]


def _maybe_str(value: float, as_string: bool) -> float | str:
    return repr(float(value)) if as_string else float(value)


def make_label_object(rng: np.random.Generator, cam: FixtureCamera, image_size: tuple[int, int]) -> dict[str, Any] | None:
    """One label/camera entry for an object on the ground in view, or None after too many misses."""
    if rng.random() < IGNORE_PROBABILITY:
        name, base = IGNORE_NAMES[int(rng.integers(len(IGNORE_NAMES)))], CLASS_SIZES["Car"]
    else:
        cls = list(CLASS_SIZES)[int(rng.choice(len(CLASS_SIZES), p=CLASS_WEIGHTS / CLASS_WEIGHTS.sum()))]
        name, base = _name_variant(rng, cls), CLASS_SIZES[cls]
    for _ in range(50):
        ground = _ground_point(rng, cam, image_size)
        if ground is None:
            continue
        lwh = np.array(base) * rng.uniform(0.9, 1.1, size=3)
        yaw = float(rng.uniform(-math.pi, math.pi))
        center = np.array([ground[0], ground[1], cam.ground_z + lwh[2] / 2.0])
        box = _box2d(cam, box_corners_lidar(center, lwh, yaw), image_size)
        if box is None:
            continue
        (x1, y1, x2, y2), truncated = box
        strings = rng.random() < 0.3
        return {
            "type": name,
            "truncated_state": "1" if truncated else "0",
            "occluded_state": str(int(rng.integers(3))),
            "alpha": "0",
            "2d_box": {"xmin": x1, "ymin": y1, "xmax": x2, "ymax": y2},
            "3d_dimensions": {k: _maybe_str(v, strings) for k, v in zip("hwl", (lwh[2], lwh[1], lwh[0]))},
            "3d_location": {k: _maybe_str(v, strings) for k, v in zip("xyz", center)},
            "rotation": _maybe_str(yaw, strings),
        }
    return None


def perturb_for_lidar(rng: np.random.Generator, obj: dict[str, Any]) -> dict[str, Any]:
    """The label/virtuallidar twin: the same object a few centimetres and a little yaw away."""
    out = json.loads(json.dumps(obj))
    loc = out["3d_location"]
    loc["x"] = float(loc["x"]) + float(rng.normal(0.0, 0.05))
    loc["y"] = float(loc["y"]) + float(rng.normal(0.0, 0.05))
    out["rotation"] = float(out["rotation"]) + float(rng.normal(0.0, 0.01))
    return out


def tiny_jpeg(image_size: tuple[int, int], tag: int = 0) -> bytes:
    """A small JPEG (a grey road under a blue sky) whose first row encodes `tag` in black and
    white blocks, so that every frame's pixels differ, as real frames' do (merge deduplicates
    images by content and would otherwise fold the whole fixture into one image)."""
    w, h = image_size
    pixels = np.zeros((h, w, 3), dtype=np.uint8)
    pixels[: h // 3] = (135, 170, 210)
    pixels[h // 3:] = (90, 90, 95)
    bits = [(tag >> k) & 1 for k in range(24)]
    block = max(1, w // 24)
    for k, bit in enumerate(bits[: w // block]):
        pixels[: max(1, h // 8), k * block:(k + 1) * block] = 255 if bit else 0
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format="JPEG", quality=70)
    return buf.getvalue()


def _dump(path: Path, obj: Any) -> None:
    path.write_text(json.dumps(obj))


def _extrinsic_json(cam: FixtureCamera, style: str, index: int) -> dict[str, Any]:
    if style == "tr" or (style == "mixed" and index % 3 == 2):
        return {"Tr_velo_to_cam": np.hstack([cam.rotation, cam.translation[:, None]]).tolist()}
    return {"rotation": cam.rotation.tolist(), "translation": cam.translation.reshape(3, 1).tolist()}


def _data_info_entry(key: str, index: int, variant: str, key_style: str) -> dict[str, Any]:
    lidar_key = "label_lidar_std_path" if key_style == "std" else ("label_virtuallidar_path" if variant == "i" else "label_lidar_path")
    entry: dict[str, Any] = {
        "image_path": f"image/{key}.jpg",
        "pointcloud_path": f"velodyne/{key}.pcd",
        "calib_camera_intrinsic_path": f"calib/camera_intrinsic/{key}.json",
        "calib_virtuallidar_to_camera_path": f"calib/virtuallidar_to_camera/{key}.json",
        ("label_camera_std_path" if key_style == "std" else "label_camera_path"): f"label/camera/{key}.json",
        lidar_key: f"label/virtuallidar/{key}.json",
    }
    if variant == "i":
        run = index // I_RUN
        stamp = T0_US + run * 300_000_000 + (index % I_RUN) * 1_000_000
        entry.update(intersection_loc=LOCATIONS[run % len(LOCATIONS)], image_timestamp=str(stamp),
                     pointcloud_timestamp=str(stamp - 40_000))
    else:
        batch = index // C_BATCH
        stamp = T0_US + batch * 600_000_000 + (index % C_BATCH) * 100_000
        entry.update(image_timestamp=str(stamp), pointcloud_timestamp=str(stamp - 40_000),
                     calib_virtuallidar_to_world_path=f"calib/virtuallidar_to_world/{key}.json",
                     batch_id=str(batch), intersection_loc=LOCATIONS[batch % len(LOCATIONS)],
                     batch_start_id=f"{batch * C_BATCH:06d}", batch_end_id=f"{batch * C_BATCH + C_BATCH - 1:06d}")
    return entry


def write_dair_tree(root: str | Path, n_frames: int, seed: int = 0, variant: str = "i",
                    image_size: tuple[int, int] = (96, 54), key_style: str = "std",
                    extrinsic_style: str = "rt", objects: tuple[int, int] = (4, 14)) -> DairFixture:
    """Write n_frames complete frames under root (the infrastructure-side folder) and return the truth.

    variant: "i" (DAIR-V2X-I: intersection and timestamps) or "c" (DAIR-V2X-C: adds batch fields and
    calib/virtuallidar_to_world). key_style: "std" (label_*_std_path, as the official code reads)
    or "readme" (label_camera_path and label_virtuallidar_path / label_lidar_path, as the README
    writes). extrinsic_style: "rt" (rotation + translation), "tr" (Tr_velo_to_cam 3x4) or "mixed"
    (every third frame Tr_velo_to_cam). objects: inclusive range of labelled objects per frame.
    """
    if variant not in VARIANTS or key_style not in KEY_STYLES or extrinsic_style not in EXTRINSIC_STYLES:
        raise ValueError(f"variant in {VARIANTS}, key_style in {KEY_STYLES}, extrinsic_style in {EXTRINSIC_STYLES}")
    root = Path(root)
    folders = ["image", "calib/camera_intrinsic", "calib/virtuallidar_to_camera", "label/camera", "label/virtuallidar"]
    if variant == "c":
        folders.append("calib/virtuallidar_to_world")
    for folder in folders:
        (root / folder).mkdir(parents=True, exist_ok=True)
    keys, cameras, data_info = [], [], []
    for index in range(n_frames):
        key = f"{index:06d}"
        cam = _write_frame(root, key, index, seed, variant, tuple(image_size), extrinsic_style, objects,
                           tiny_jpeg(tuple(image_size), tag=index))
        keys.append(key)
        cameras.append(cam)
        data_info.append(_data_info_entry(key, index, variant, key_style))
    _dump(root / "data_info.json", data_info)
    return DairFixture(root, variant, keys, cameras)


def _write_frame(root: Path, key: str, index: int, seed: int, variant: str, image_size: tuple[int, int],
                 extrinsic_style: str, objects: tuple[int, int], image_bytes: bytes) -> FixtureCamera:
    rng = np.random.default_rng([seed, index])
    cam = make_camera(rng, image_size)
    labels = [o for o in (make_label_object(rng, cam, image_size)
                          for _ in range(int(rng.integers(objects[0], objects[1] + 1)))) if o is not None]
    (root / "image" / f"{key}.jpg").write_bytes(image_bytes)
    _dump(root / "calib/camera_intrinsic" / f"{key}.json",
          {"cam_D": rng.normal(0.0, 0.01, size=5).tolist(), "cam_K": cam.K.reshape(-1).tolist()})
    _dump(root / "calib/virtuallidar_to_camera" / f"{key}.json", _extrinsic_json(cam, extrinsic_style, index))
    _dump(root / "label/camera" / f"{key}.json", labels)
    _dump(root / "label/virtuallidar" / f"{key}.json", [perturb_for_lidar(rng, o) for o in labels])
    if variant == "c":
        _dump(root / "calib/virtuallidar_to_world" / f"{key}.json",
              {"rotation": np.eye(3).tolist(), "translation": [[2600.0], [1700.0], [20.0]],
               "relative_error": {"delta_x": "", "delta_y": ""}})
    return cam


# ---------------------------------------------------------------------------------------------
# DAIR-V2X-C as a whole: vehicle side, world calibrations, cooperative pairs
# ---------------------------------------------------------------------------------------------

WORLD_ORIGIN = np.array([2600.0, 1700.0, 20.0])
"""Where write_dair_tree's variant 'c' puts every infrastructure virtual LiDAR (identity rotation)."""
VEHICLE_LIDAR_HEIGHT = 1.9  # the vehicle LiDAR above the ground, metres
VEHICLE_ID0 = 10000  # vehicle DAIR ids start here, apart from the infrastructure ones
VEHICLE_IMAGE_SIZE = (128, 72)  # not the infrastructure's: the vehicle camera has its own K
VEHICLE_DELAY_US = 30_000  # the vehicle image is taken this long after its pair's infrastructure image


@dataclass(frozen=True)
class CooperativeFixture:
    root: Path  # the cooperative root
    infrastructure: DairFixture
    vehicle_keys: list[str]  # vehicle_keys[i] pairs with infrastructure.keys[pair_infra[i]]
    pair_infra: list[int]
    offsets: list[tuple[float, float] | None]  # per pair; None where system_error_offset is ""


def _rigid(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, translation
    return m


def _rt_json(m: np.ndarray) -> dict[str, Any]:
    return {"rotation": m[:3, :3].tolist(), "translation": m[:3, 3].reshape(3, 1).tolist()}


def _vehicle_camera(rng: np.random.Generator) -> FixtureCamera:
    """A forward camera on the roof: 0.3 m below and 0.5 m ahead of the LiDAR, pitched 0-4 degrees down."""
    w, h = VEHICLE_IMAGE_SIZE
    pitch = math.radians(rng.uniform(0.0, 4.0))
    f = (w / 2.0) / math.tan(math.radians(rng.uniform(55.0, 70.0)) / 2.0)
    K = np.array([[f, 0.0, w / 2.0 - 0.5], [0.0, f, h / 2.0 - 0.5], [0.0, 0.0, 1.0]])
    camera_to_lidar = LEVEL_CAMERA_TO_LIDAR @ _rot_x(-pitch)
    position = np.array([0.5, 0.0, -0.3])
    rotation = camera_to_lidar.T
    return FixtureCamera(K, rotation, -rotation @ position, VEHICLE_LIDAR_HEIGHT - 0.3, pitch, -VEHICLE_LIDAR_HEIGHT)


def _vehicle_pose(rng: np.random.Generator, infra: FixtureCamera) -> np.ndarray:
    """Vehicle LiDAR to world: on the ground 6-10 m behind the pole's foot, heading where the pole looks."""
    axis = infra.rotation.T[:, 2]  # the pole camera's optical axis in its virtual-LiDAR frame
    heading = math.atan2(axis[1], axis[0]) + rng.uniform(-0.1, 0.1)
    foot = infra.center[:2] - rng.uniform(6.0, 10.0) * np.array([math.cos(heading), math.sin(heading)])
    z = infra.ground_z + VEHICLE_LIDAR_HEIGHT
    return _rigid(_rot_z(heading), WORLD_ORIGIN + np.array([foot[0], foot[1], z]))


def _label_to_vehicle(obj: dict[str, Any], world_from_infra: np.ndarray, vehicle_from_world: np.ndarray,
                      cam: FixtureCamera, world_id: int) -> dict[str, Any] | None:
    """An infrastructure label entry seen from the vehicle: same world box, its own 2D box; None if not in view."""
    if "3d_location" not in obj:
        return None
    loc, dims = obj["3d_location"], obj["3d_dimensions"]
    center_world = world_from_infra @ np.array([float(loc["x"]), float(loc["y"]), float(loc["z"]), 1.0])
    center = (vehicle_from_world @ center_world)[:3]
    m = vehicle_from_world @ world_from_infra
    yaw = float(obj["rotation"]) + math.atan2(m[1, 0], m[0, 0])
    lwh = np.array([float(dims["l"]), float(dims["w"]), float(dims["h"])])
    box = _box2d(cam, box_corners_lidar(center, lwh, yaw), VEHICLE_IMAGE_SIZE)
    if box is None:
        return None
    (x1, y1, x2, y2), truncated = box
    return {"type": obj["type"], "truncated_state": "1" if truncated else "0", "occluded_state": obj["occluded_state"],
            "alpha": "0", "2d_box": {"xmin": x1, "ymin": y1, "xmax": x2, "ymax": y2},
            "3d_dimensions": {"h": lwh[2], "w": lwh[1], "l": lwh[0]},
            "3d_location": {"x": center[0], "y": center[1], "z": center[2]}, "rotation": yaw,
            "fixture_world_id": world_id}


def write_cooperative_tree(root: str | Path, n_pairs: int, seed: int = 0, image_size: tuple[int, int] = (96, 54),
                           objects: tuple[int, int] = (6, 14)) -> CooperativeFixture:
    """A DAIR-V2X-C root: infrastructure-side/ (write_dair_tree variant 'c'), vehicle-side/, cooperative/.

    Pair i joins infrastructure frame i and vehicle frame VEHICLE_ID0 + i; one more vehicle frame
    pairs again with infrastructure frame 0 (an infrastructure frame in two pairs). Each pair is one
    world: the vehicle labels are the infrastructure's world boxes seen from the vehicle (a
    `fixture_world_id` field names the infrastructure label index), so shared objects agree in the
    world. Every other pair has a system_error_offset; its infrastructure virtuallidar_to_world
    file is then off by minus that offset, as the official transform's correction implies.
    """
    root = Path(root)
    infra = write_dair_tree(root / "infrastructure-side", n_pairs, seed=seed, variant="c", image_size=image_size,
                            objects=objects)
    vroot = root / "vehicle-side"
    for folder in ("image", "calib/camera_intrinsic", "calib/lidar_to_camera", "calib/lidar_to_novatel",
                   "calib/novatel_to_world", "label/camera", "label/lidar"):
        (vroot / folder).mkdir(parents=True, exist_ok=True)
    (root / "cooperative").mkdir(parents=True, exist_ok=True)
    pair_infra = list(range(n_pairs)) + ([0] if n_pairs else [])
    vehicle_keys, offsets, vehicle_info, coop_info = [], [], [], []
    for i, j in enumerate(pair_infra):
        rng = np.random.default_rng([seed, 0xC0, i])
        key = f"{VEHICLE_ID0 + i:06d}"
        offset = (float(rng.uniform(0.3, 1.5)), float(rng.uniform(-1.5, -0.3))) if i % 2 else None
        _write_vehicle_frame(vroot, root / "infrastructure-side", key, infra.keys[j], infra.cameras[j], rng, i)
        if offset is not None and i < n_pairs:  # the repeated pair shares frame 0's file: no offset there
            _dump(root / "infrastructure-side/calib/virtuallidar_to_world" / f"{infra.keys[j]}.json",
                  {"rotation": np.eye(3).tolist(), "translation": (WORLD_ORIGIN - [*offset, 0.0]).reshape(3, 1).tolist(),
                   "relative_error": {"delta_x": "", "delta_y": ""}})
        elif i >= n_pairs:
            offset = None
        vehicle_keys.append(key)
        offsets.append(offset)
        vehicle_info.append(_vehicle_info_entry(key, j))
        coop_info.append({"infrastructure_image_path": f"infrastructure-side/image/{infra.keys[j]}.jpg",
                          "infrastructure_pointcloud_path": f"infrastructure-side/velodyne/{infra.keys[j]}.pcd",
                          "vehicle_image_path": f"vehicle-side/image/{key}.jpg",
                          "vehicle_pointcloud_path": f"vehicle-side/velodyne/{key}.pcd",
                          "cooperative_label_path": f"cooperative/label_world/{key}.json",
                          "system_error_offset": "" if offset is None else {"delta_x": offset[0], "delta_y": offset[1]}})
    _dump(vroot / "data_info.json", vehicle_info)
    _dump(root / "cooperative" / "data_info.json", coop_info)
    return CooperativeFixture(root, infra, vehicle_keys, pair_infra, offsets)


def _vehicle_info_entry(key: str, infra_index: int) -> dict[str, Any]:
    batch = infra_index // C_BATCH
    stamp = T0_US + batch * 600_000_000 + (infra_index % C_BATCH) * 100_000 + VEHICLE_DELAY_US
    return {"image_path": f"image/{key}.jpg", "pointcloud_path": f"velodyne/{key}.pcd", "image_timestamp": str(stamp),
            "pointcloud_timestamp": str(stamp - 40_000), "calib_camera_intrinsic_path": f"calib/camera_intrinsic/{key}.json",
            "calib_lidar_to_camera_path": f"calib/lidar_to_camera/{key}.json",
            "calib_lidar_to_novatel_path": f"calib/lidar_to_novatel/{key}.json",
            "calib_novatel_to_world_path": f"calib/novatel_to_world/{key}.json",
            "label_camera_std_path": f"label/camera/{key}.json", "label_lidar_std_path": f"label/lidar/{key}.json",
            "batch_id": str(batch), "intersection_loc": LOCATIONS[batch % len(LOCATIONS)],
            "batch_start_id": f"{batch * C_BATCH:06d}", "batch_end_id": f"{batch * C_BATCH + C_BATCH - 1:06d}"}


def _write_vehicle_frame(vroot: Path, iroot: Path, key: str, infra_key: str, infra: FixtureCamera,
                         rng: np.random.Generator, index: int) -> None:
    """One vehicle frame: calibrations (lidar_to_novatel a small yaw and offset) and the pair's world boxes."""
    cam = _vehicle_camera(rng)
    world_from_vehicle = _vehicle_pose(rng, infra)
    novatel_from_lidar = _rigid(_rot_z(rng.uniform(-0.05, 0.05)), np.array([rng.uniform(-1, 1), 0.2, -1.2]))
    world_from_novatel = world_from_vehicle @ np.linalg.inv(novatel_from_lidar)
    world_from_infra = _rigid(np.eye(3), WORLD_ORIGIN)  # the truth (the file may carry an offset error)
    labels = json.loads((iroot / "label/camera" / f"{infra_key}.json").read_text())
    seen = [_label_to_vehicle(o, world_from_infra, np.linalg.inv(world_from_vehicle), cam, n) for n, o in enumerate(labels)]
    (vroot / "image" / f"{key}.jpg").write_bytes(tiny_jpeg(VEHICLE_IMAGE_SIZE, tag=VEHICLE_ID0 + index))
    _dump(vroot / "calib/camera_intrinsic" / f"{key}.json", {"cam_D": [0.0] * 5, "cam_K": cam.K.reshape(-1).tolist()})
    _dump(vroot / "calib/lidar_to_camera" / f"{key}.json",
          {"rotation": cam.rotation.tolist(), "translation": cam.translation.reshape(3, 1).tolist()})
    _dump(vroot / "calib/lidar_to_novatel" / f"{key}.json", {"transform": _rt_json(novatel_from_lidar)})
    _dump(vroot / "calib/novatel_to_world" / f"{key}.json", _rt_json(world_from_novatel))
    vehicle_labels = [o for o in seen if o is not None]
    _dump(vroot / "label/camera" / f"{key}.json", vehicle_labels)
    _dump(vroot / "label/lidar" / f"{key}.json", vehicle_labels)
