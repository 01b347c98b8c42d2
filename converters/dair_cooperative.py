"""DAIR-V2X-C as a whole: the infrastructure and the vehicle side of a cooperative root, paired.

A cooperative root holds `infrastructure-side/`, `vehicle-side/` and `cooperative/data_info.json`.
Each side is converted by omnigen.converters.dair's DairConverter with its own names (DairSide);
this module adds what only the pairing knows (docs/converters-dair.md, "DAIR-V2X-C as a whole"):

- `pair`: `dair-v2x-c-pair-<vehicle id>` on both frames of a cooperative pair; an infrastructure
  frame listed in several pairs keeps the first (the others are counted). The vehicle frame takes
  its pair's infrastructure group, so a split never separates the two.
- `sequence` per `batch_id` (`dair-v2x-c-batch-<id>`, both sides) and `timestamp`: seconds from the
  batch's first image (both sides), from data_info's microsecond timestamps.
- `camera_to_world` where the files give it: infrastructure virtuallidar_to_world o
  inv(virtuallidar_to_camera), plus the pair's system_error_offset (x, y), as the official
  cooperative transform applies it; vehicle novatel_to_world o lidar_to_novatel o inv(lidar_to_camera).
  A missing file gives null.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omnigen.converters.common import ConvertedFrame, SourceError
from omnigen.converters.dair import (
    DATA_INFO,
    DATA_INFO_MAX_BYTES,
    INFRASTRUCTURE,
    INFRASTRUCTURE_SIDE,
    SOURCE_C,
    VEHICLE,
    DairConverter,
    DairOptions,
    Extrinsics,
    FrameInfo,
    _short,
    _text,
    _timestamps,
    as_matrix,
    as_number,
    nearest_rotation,
    read_json,
)
from omnigen.plausible import MAX_WORLD_COORDINATE_M

VEHICLE_SIDE = "vehicle-side"
COOPERATIVE_INFO = Path("cooperative") / DATA_INFO

WORLD_TRANSLATION_MAX_M = MAX_WORLD_COORDINATE_M
"""Largest world translation accepted: DAIR-V2X's world is a map projection (kilometres from its
origin), so the 100 m bound of camera extrinsics does not apply; the one bound `omnigen validate`
holds a camera position to (omnigen.plausible), so the two cannot drift apart."""

INFRA_WORLD = (("calib_virtuallidar_to_world_path",), ("calib/virtuallidar_to_world",))
VEHICLE_TO_NOVATEL = (("calib_lidar_to_novatel_path",), ("calib/lidar_to_novatel",))
NOVATEL_TO_WORLD = (("calib_novatel_to_world_path",), ("calib/novatel_to_world",))


def is_cooperative(src: Path) -> bool:
    """A DAIR-V2X-C root with the cooperative pairing file (else `convert dair` behaves as before)."""
    return (Path(src) / COOPERATIVE_INFO).is_file()


# ---------------------------------------------------------------------------------------------
# Rigid transforms
# ---------------------------------------------------------------------------------------------


def parse_rigid(data: Any, file: Path) -> np.ndarray:
    """A 4x4 pose from `{rotation, translation}` (or wrapped in `transform`), rotation made proper."""
    if isinstance(data, dict) and isinstance(data.get("transform"), dict):
        data = data["transform"]
    if not isinstance(data, dict):
        raise SourceError(file, "", f"expected a JSON object with rotation and translation, got {type(data).__name__}")
    rotation = nearest_rotation(as_matrix(data.get("rotation"), (3, 3), file, "rotation"), file, "rotation")
    translation = as_matrix(data.get("translation"), (3,), file, "translation")
    if np.abs(translation).max() > WORLD_TRANSLATION_MAX_M:
        raise SourceError(file, "translation", f"beyond {WORLD_TRANSLATION_MAX_M:g} m: {translation.tolist()}")
    return pose(rotation, translation)


def pose(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, translation
    return m


def camera_to_world(to_world: np.ndarray, lidar_to_camera: np.ndarray, file: Path) -> np.ndarray:
    """to_world o inv(lidar_to_camera), its rotation re-orthonormalised (the schema wants a proper one)."""
    r, t = lidar_to_camera[:3, :3], lidar_to_camera[:3, 3]
    m = to_world @ pose(r.T, -r.T @ t)
    m[:3, :3] = nearest_rotation(m[:3, :3], file, "rotation")
    return m


# ---------------------------------------------------------------------------------------------
# Pairs
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Pair:
    pair_id: str
    infrastructure: str  # DAIR ids
    vehicle: str
    offset: tuple[float, float]  # system_error_offset (delta_x, delta_y), 0 where ""


@dataclass
class Pairs:
    by_infrastructure: dict[str, Pair]
    by_vehicle: dict[str, Pair]
    repeated_infrastructure: set[str]  # infrastructure ids named by a later pair too (kept the first)
    errors: dict[str, SourceError]


def read_pairs(root: Path) -> Pairs:
    """cooperative/data_info.json: an entry per pair; a bad entry is an error of its own, not the file's."""
    path = root / COOPERATIVE_INFO
    data = read_json(path, max_bytes=DATA_INFO_MAX_BYTES)
    if not isinstance(data, list):
        raise SourceError(path, "", f"expected a JSON list of pairs, got {type(data).__name__}")
    pairs = Pairs({}, {}, set(), {})
    for i, entry in enumerate(data):
        try:
            pair = _pair(entry, i, path)
        except SourceError as exc:
            pairs.errors[f"cooperative/#{i}"] = exc
            continue
        if pair.vehicle in pairs.by_vehicle:
            pairs.errors[f"cooperative/#{i}"] = SourceError(path, f"[{i}].vehicle_image_path",
                                                            f"vehicle frame {pair.vehicle} is in an earlier pair")
            continue
        pairs.by_vehicle[pair.vehicle] = pair
        if pair.infrastructure in pairs.by_infrastructure:
            pairs.repeated_infrastructure.add(pair.infrastructure)
        else:
            pairs.by_infrastructure[pair.infrastructure] = pair
    return pairs


def _pair(entry: Any, i: int, path: Path) -> Pair:
    if not isinstance(entry, dict):
        raise SourceError(path, f"[{i}]", f"expected a JSON object, got {type(entry).__name__}")
    ids = []
    for key in ("infrastructure_image_path", "vehicle_image_path"):
        value = entry.get(key)
        if not isinstance(value, str) or not value.strip():
            raise SourceError(path, f"[{i}].{key}", "missing" if value is None else f"expected a path, got {_short(value)}")
        ids.append(Path(value).stem)
    return Pair(f"{SOURCE_C}-pair-{ids[1]}", ids[0], ids[1], _offset(entry.get("system_error_offset"), path, i))


def _offset(value: Any, path: Path, i: int) -> tuple[float, float]:
    """system_error_offset: `{delta_x, delta_y}` metres, or "" (none)."""
    if value is None or value == "":
        return 0.0, 0.0
    where = f"[{i}].system_error_offset"
    if not isinstance(value, dict):
        raise SourceError(path, where, f"expected an object with delta_x, delta_y, got {_short(value)}")
    return as_number(value.get("delta_x"), path, where + ".delta_x"), as_number(value.get("delta_y"), path, where + ".delta_y")


# ---------------------------------------------------------------------------------------------
# The converter
# ---------------------------------------------------------------------------------------------


class CooperativeConverter:
    """Keys `infrastructure/<id>` and `vehicle/<id>`; each frame converted by its side's DairConverter,
    then given its pair, sequence, timestamp, camera_to_world and (vehicle) its pair's group."""

    def __init__(self, src: Path, options: DairOptions = DairOptions(), side: str = "both"):
        src = Path(src)
        options = dataclasses.replace(options, source=SOURCE_C)
        self.root = src
        self.sides = ("infrastructure", "vehicle") if side == "both" else (side,)
        self.converters = {"infrastructure": DairConverter(src / INFRASTRUCTURE_SIDE, options, INFRASTRUCTURE),
                           "vehicle": DairConverter(src / VEHICLE_SIDE, options, VEHICLE)}
        self.source = SOURCE_C
        self.options = options
        self.pairs = read_pairs(src)
        self.clock = _batch_clock(self.converters)
        self.vehicle_groups = self._vehicle_groups()

    def keys(self) -> list[str]:
        keys = [f"{side}/{k}" for side in self.sides for k in self.converters[side].keys()]
        return keys + sorted(self.pairs.errors)

    def convert(self, key: str) -> ConvertedFrame:
        if key in self.pairs.errors:
            raise self.pairs.errors[key]
        side, dair_id = key.split("/", 1)
        converted, ext, ext_path = self.converters[side].convert_posed(dair_id)
        fields = self._fields(side, dair_id, ext, ext_path)
        stats = dict(converted.stats, frames_camera_to_world_null=int(fields["camera_to_world"] is None),
                     infrastructure_frames_in_a_later_pair=int(side == "infrastructure"
                                                               and dair_id in self.pairs.repeated_infrastructure))
        return dataclasses.replace(converted, record=dataclasses.replace(converted.record, **fields), stats=stats)

    def _fields(self, side: str, dair_id: str, ext: Extrinsics, ext_path: Path) -> dict[str, Any]:
        converter = self.converters[side]
        f = converter.frames[dair_id]
        by_side = self.pairs.by_infrastructure if side == "infrastructure" else self.pairs.by_vehicle
        pair = by_side.get(dair_id)
        sequence, timestamp = self.clock.get(f"{side}/{dair_id}", (None, None))
        fields: dict[str, Any] = {"pair": None if pair is None else pair.pair_id, "sequence": sequence,
                                  "timestamp": timestamp,
                                  "camera_to_world": self._pose(side, converter, f, pair, ext, ext_path)}
        if side == "vehicle" and dair_id in self.vehicle_groups:
            fields["group"] = self.vehicle_groups[dair_id]
        return fields

    def _pose(self, side: str, converter: DairConverter, f: FrameInfo, pair: Pair | None, ext: Extrinsics,
              ext_path: Path) -> np.ndarray | None:
        """camera_to_world from the frame's extrinsics (`ext`, read from `ext_path` when it was
        converted) and the side's world files; None when one of them is absent."""
        lidar_to_camera = pose(ext.rotation, ext.translation)
        chain = [INFRA_WORLD] if side == "infrastructure" else [NOVATEL_TO_WORLD, VEHICLE_TO_NOVATEL]
        to_world = np.eye(4)
        for keys, dirs in chain:
            path, named_by = converter.resolve(f, keys, dirs)
            if not path.is_file():
                return None
            to_world = to_world @ parse_rigid(read_json(path, f"{named_by}, frame {f.key}"), path)
        if side == "infrastructure" and pair is not None:
            to_world[:2, 3] += pair.offset
        return camera_to_world(to_world, lidar_to_camera, ext_path)

    def _vehicle_groups(self) -> dict[str, str | None]:
        """A paired vehicle frame's group is its infrastructure frame's (merge keeps a group whole)."""
        infra = self.converters["infrastructure"]
        return {vid: infra.groups.get(p.infrastructure) for vid, p in self.pairs.by_vehicle.items()
                if p.infrastructure in infra.frames}


def _batch_clock(converters: dict[str, DairConverter]) -> dict[str, tuple[str, float | None]]:
    """`side/id` -> (sequence, seconds from the batch's first image on either side) for frames with a batch_id."""
    batches: dict[str, list[tuple[str, int | None]]] = {}
    for side, converter in converters.items():
        stamps, _ = _timestamps(converter.tree.frames, converter.tree.data_info)
        for f in converter.tree.frames:
            batch = _text(f.info, "batch_id")
            if batch is not None:
                batches.setdefault(f"{SOURCE_C}-batch-{batch}", []).append((f"{side}/{f.key}", stamps.get(f.key)))
    clock: dict[str, tuple[str, float | None]] = {}
    for sequence, members in batches.items():
        known = [s for _, s in members if s is not None]
        first = min(known) if known else 0
        for key, stamp in members:
            clock[key] = (sequence, None if stamp is None else (stamp - first) / 1e6)
    return clock


def check_side(src: Path, side: str) -> None:
    """--side vehicle needs a cooperative root (the vehicle side is found only there); --side
    infrastructure converts any DAIR root as if it had no cooperative/."""
    if side == "vehicle" and not is_cooperative(src):
        raise SourceError(Path(src) / COOPERATIVE_INFO, "", "missing: --side vehicle needs a DAIR-V2X-C cooperative root")

