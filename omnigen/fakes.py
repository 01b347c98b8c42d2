"""Plausible random datasets for tests and benchmarks (never for training).

Frames are built with the real geometry (ObjectRecord.from_box), so every derived field obeys the
contract; only the scene is random. One numpy Generator per frame, seeded from (seed, index), so
any frame can be regenerated alone and a dataset is the same however it is produced.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
from PIL import Image

from omnigen.conventions import FINE_CLASSES, SCHEMA2_FRAME_FIELDS, SCHEMA2_OBJECT_FIELDS, SCHEMA_VERSION, SOURCES, VIEWS
from omnigen.dataset import Dataset, record_path
from omnigen.files import atomic_write_bytes, dumps_json
from omnigen.camera import intrinsics_from_fov, look_at
from omnigen.geometry import Box3D, plane_from_height_pitch, rot_x, rot_z
from omnigen.progress import progress
from omnigen.record import FrameRecord, IgnoreRegion, ObjectRecord, SyntheticInfo
from omnigen.writer import DatasetWriter

TYPICAL_DIMS = {  # l, w, h in metres: rough means, enough for plausible fakes
    "car": (4.2, 1.8, 1.5), "van": (5.0, 2.0, 2.1), "truck": (8.0, 2.5, 3.2), "bus": (11.0, 2.6, 3.2),
    "tram": (25.0, 2.6, 3.4), "pedestrian": (0.6, 0.6, 1.75), "cyclist": (1.8, 0.6, 1.7),
    "motorcyclist": (2.0, 0.8, 1.6), "tricyclist": (2.6, 1.2, 1.7), "barrow": (1.2, 0.6, 1.0),
    "traffic_cone": (0.4, 0.4, 0.7), "misc": (2.0, 1.5, 1.5),
}

VIEW_CAMERAS = {  # view: (height range m, pitch range degrees)
    "ego": ((1.4, 1.9), (-3.0, 5.0)),
    "infrastructure": ((5.0, 12.0), (10.0, 45.0)),
    "aerial": ((20.0, 120.0), (30.0, 89.0)),
}


def random_frame(seed: int, index: int, source: str = "synthetic", view: str = "ego", n_objects: int = 8,
                 width: int = 320, height: int = 192, sequence: bool = False) -> FrameRecord:
    """One frame of upright objects on a flat ground seen by a pitched camera.

    `sequence`: also fill the schema-2 fields (with_sequence_fields); the frame is otherwise the same.
    """
    rng = np.random.default_rng([seed, index])
    (h_lo, h_hi), (p_lo, p_hi) = VIEW_CAMERAS[view]
    cam_height = rng.uniform(h_lo, h_hi)
    pitch = math.radians(rng.uniform(p_lo, p_hi))
    K = intrinsics_from_fov(math.radians(rng.uniform(40, 100)), width, height)
    plane = plane_from_height_pitch(cam_height, pitch)
    # World (x right, y forward, z up) -> camera: level camera first, then pitched down.
    level = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    world_to_cam = rot_x(pitch) @ level
    objects: list[ObjectRecord] = []
    tries = 0
    while len(objects) < n_objects and tries < n_objects * 20:
        tries += 1
        category = FINE_CLASSES[int(rng.integers(len(FINE_CLASSES)))]
        dims = np.array(TYPICAL_DIMS[category]) * rng.uniform(0.85, 1.15, 3)
        reach = max(cam_height / math.tan(max(pitch, math.radians(10))), 8.0)
        ground = np.array([rng.uniform(-0.6, 0.6) * reach, rng.uniform(0.3, 2.5) * reach, -cam_height + dims[2] / 2])
        box = Box3D(world_to_cam @ ground, dims, world_to_cam @ rot_z(rng.uniform(-math.pi, math.pi)))
        occlusion = float(rng.uniform(0, 1))
        obj = ObjectRecord.from_box(
            category, len(objects) + 1, box, K, width, height,
            occlusion=occlusion if source == "synthetic" else None,
            occlusion_level=min(int(occlusion * 3), 2) if source == "synthetic" else int(rng.integers(0, 4)),
            bbox_source=None, source_attributes={} if source == "synthetic" else {"fake": True},
        )
        if obj is not None:
            objects.append(obj)
    frame_id = f"{source}-{index:06d}"
    synthetic = None
    if source == "synthetic":
        synthetic = SyntheticInfo(seed=seed, scene="fake", rig=view, weather={"fog": 0.0},
                                  lighting={"sun_elevation": 0.6}, depth=f"depth/{frame_id}.exr",
                                  instance=f"instance/{frame_id}.png")
    ignore = [IgnoreRegion(np.array([1.0, 2.0, 30.0, 40.0]), "DontCare")] if index % 5 == 0 else []
    rec = FrameRecord(frame_id=frame_id, source=source, view=view, image=f"images/{frame_id}.png", width=width,
                      height=height, K=K, objects=objects, ignore_regions=ignore, ground_plane=plane,
                      camera_height=plane.camera_height, camera_pitch=plane.camera_pitch,
                      group=f"{source}-g{index // 10}", synthetic=synthetic)
    return with_sequence_fields(rec, seed, index, world_to_cam, cam_height) if sequence else rec


TRACKS_PER_FRAME = 100
"""Track ids a random sequenced frame may use (random_frame draws fewer objects than this)."""


def with_sequence_fields(rec: FrameRecord, seed: int, index: int, world_to_cam: np.ndarray,
                         cam_height: float) -> FrameRecord:
    """`rec` as frame index % 10 of sequence index // 10 at 10 fps: sequence, timestamp, a pair id
    (frames index and index ^ 1 as a cooperative pair), camera_to_world (world z up, origin on the
    ground under the camera), each object's track_id (TRACKS_PER_FRAME * (index % 10) + its
    instance id: the frames' random objects are different objects, so no track spans two frames,
    which the cooperation checks would rightly call a jump) and a world velocity. Drawn from a
    Generator of its own, so that the rest of the frame is the frame random_frame gives without them."""
    rng = np.random.default_rng([seed, index, 1])
    sequence = f"{rec.source}-seq{index // 10:03d}"
    pose = np.eye(4)
    pose[:3, :3] = world_to_cam.T
    pose[2, 3] = cam_height
    first = TRACKS_PER_FRAME * (index % 10)
    objects = [replace(o, track_id=first + o.instance_id, velocity=np.array([*rng.uniform(-10, 10, 2), 0.0]))
               for o in rec.objects]
    return replace(rec, objects=objects, sequence=sequence, timestamp=(index % 10) / 10,
                   pair=f"{sequence}-pair{index % 10 // 2:06d}", camera_to_world=pose)


def schema1_bytes(record: FrameRecord) -> bytes:
    """A record file as omnigen wrote it before schema 2 (no sequence, pair, pose or track
    fields), for tests that older datasets still read."""
    d = record.to_dict()
    d["schema_version"] = 1
    for key in SCHEMA2_FRAME_FIELDS:
        del d[key]
    for o in d["objects"]:
        for key in SCHEMA2_OBJECT_FIELDS:
            del o[key]
    return dumps_json(d).encode()


def write_fake_dataset(root: str | Path, n_frames: int, objects_per_frame: int = 8, seed: int = 0,
                       source: str = "synthetic", images: bool = True, show_progress: bool = False,
                       sequence: bool = False, schema: int = SCHEMA_VERSION) -> Dataset:
    """A finalized fake dataset; images (and depth/instance placeholders) are tiny but real files.

    `sequence`: frames carry the schema-2 sequence and track fields (random_frame); `schema` 1
    writes the records as schema 1 instead (schema1_bytes), as an older omnigen did.
    """
    assert source in SOURCES
    root = Path(root)
    writer = DatasetWriter(root)
    for i in progress(range(n_frames), desc="fake frames", disable=not show_progress):
        view = VIEWS[i % len(VIEWS)] if source == "synthetic" else ("ego" if source == "kitti" else "infrastructure")
        rec = random_frame(seed, i, source, view, objects_per_frame, sequence=sequence)
        if images:
            _write_files(root, rec, (i % 251, (i // 251) % 251, seed % 251))
        if schema == 1:
            atomic_write_bytes(record_path(root, rec.frame_id), schema1_bytes(rec), durable=False)
        else:
            writer.write(rec)
    return writer.finalize({"name": f"fake-{source}"}, show_progress=show_progress)


def _write_files(root: Path, rec: FrameRecord, shade: tuple[int, int, int]) -> None:
    """The frame's image, one flat colour (distinct per frame: no accidental duplicates), and
    placeholders for a rendered frame's depth and instance files."""
    (root / "images").mkdir(exist_ok=True)
    Image.new("RGB", (rec.width, rec.height), shade).save(root / rec.image)
    if rec.synthetic is not None:
        for rel in (rec.synthetic.depth, rec.synthetic.instance):
            (root / rel).parent.mkdir(exist_ok=True)
            (root / rel).write_bytes(b"placeholder")


COOPERATIVE_EYES = {  # view: camera position relative to the scene centre (x right, y forward, z up), metres
    "ego": (0.0, -22.0, 1.6), "infrastructure": (-12.0, -6.0, 7.0), "aerial": (0.0, -6.0, 45.0),
}
COOPERATIVE_FPS = 10.0
COOPERATIVE_CLASSES = ("car", "van", "pedestrian", "cyclist")


def fake_cooperative_records(seed: int = 0, n_sequences: int = 2, n_instants: int = 4, n_objects: int = 5,
                             views: tuple[str, ...] = ("ego", "infrastructure", "aerial"),
                             width: int = 320, height: int = 192) -> list[FrameRecord]:
    """Sequences of one small world seen by several static cameras at COOPERATIVE_FPS: each object
    moves at a constant world velocity, and every view labels it by projecting the same world box
    through its own pose, so the views agree to float precision (the cooperation checks' ground
    truth). The ego and infrastructure frames of an instant form a cooperative `pair`. One
    Generator per sequence (the world) and per view of it (its intrinsics, fixed over time as a
    real camera's are)."""
    records = []
    for q in range(n_sequences):
        world = _cooperative_world(np.random.default_rng([seed, q, 2]), n_objects)
        sequence = f"synthetic-coop-s{seed}-q{q:06d}"
        intrinsics = [intrinsics_from_fov(math.radians(np.random.default_rng([seed, q, v, 3]).uniform(70, 90)),
                                          width, height) for v in range(len(views))]
        for k in range(n_instants):
            for view, K in zip(views, intrinsics):
                records.append(_cooperative_frame(world, sequence, k, view, K, seed, width, height))
    return records


def _cooperative_world(rng: np.random.Generator, n_objects: int) -> list[tuple[str, np.ndarray, np.ndarray, float, np.ndarray]]:
    """(category, dims, start centre, yaw, velocity) per object, on flat ground z = 0 near the origin."""
    world = []
    for _ in range(n_objects):
        category = COOPERATIVE_CLASSES[int(rng.integers(len(COOPERATIVE_CLASSES)))]
        dims = np.array(TYPICAL_DIMS[category]) * rng.uniform(0.9, 1.1, 3)
        yaw = float(rng.uniform(-math.pi, math.pi))
        start = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), dims[2] / 2])
        velocity = np.array([math.cos(yaw), math.sin(yaw), 0.0]) * rng.uniform(0.5, 8.0)
        world.append((category, dims, start, yaw, velocity))
    return world


def _cooperative_frame(world: list, sequence: str, k: int, view: str, K: np.ndarray, seed: int,
                       width: int, height: int) -> FrameRecord:
    """One view of the world at instant k: world boxes mapped into this camera and projected."""
    t = k / COOPERATIVE_FPS
    R, trans = look_at(COOPERATIVE_EYES[view], (0.0, 0.0, 0.0))
    objects = []
    for track, (category, dims, start, yaw, velocity) in enumerate(world, start=1):
        box = Box3D(start + velocity * t, dims, rot_z(yaw)).transformed(R, trans)
        obj = ObjectRecord.from_box(category, track, box, K, width, height, track_id=track, velocity=velocity.copy())
        if obj is not None:
            objects.append(obj)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R.T, COOPERATIVE_EYES[view]
    frame_id = f"{sequence}-{view}-t{k:03d}"
    synthetic = SyntheticInfo(seed=seed, scene="fake-coop", rig=view, weather={"fog": 0.0},
                              lighting={"sun_elevation": 0.6}, depth=f"depth/{frame_id}.exr",
                              instance=f"instance/{frame_id}.png")
    return FrameRecord(frame_id=frame_id, source="synthetic", view=view, image=f"images/{frame_id}.png",
                       width=width, height=height, K=K.copy(), objects=objects, group=None, synthetic=synthetic,
                       sequence=sequence, timestamp=t,
                       pair=f"{sequence}-p{k:06d}" if view in ("ego", "infrastructure") else None,
                       camera_to_world=pose)


def write_cooperative_dataset(root: str | Path, records: list[FrameRecord] | None = None, **kwargs) -> Dataset:
    """A finalized dataset of fake_cooperative_records(**kwargs) (or of `records`), with tiny images."""
    root = Path(root)
    writer = DatasetWriter(root)
    for i, rec in enumerate(records if records is not None else fake_cooperative_records(**kwargs)):
        _write_files(root, rec, (i % 251, (i // 251) % 251, 7))
        writer.write(rec)
    return writer.finalize({"name": "fake-cooperative"}, show_progress=False)
