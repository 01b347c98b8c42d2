"""Checks across the frames of a sequence: one world seen by several cameras over time.

Each frame labels its objects in its own camera frame; `camera_to_world` maps them into the world
the sequence's frames share, and `track_id` names one physical object in every view and at every
instant. Two views that place one track at one instant in different spots, or a track that moves
faster than any road user between two instants, point at a bad pose or a bad label, which no
single record can show. `omnigen validate`, stats and the tests read these.

An instant is (sequence, timestamp rounded to INSTANT_DECIMALS): the contract has no instant id.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from itertools import combinations
from typing import Iterable

import numpy as np

from omnigen.geometry import Box3D
from omnigen.record import FrameRecord

INSTANT_DECIMALS = 6
"""Timestamps of one instant agree to 1e-6 s (the contract); rounding to it keys an instant."""
MIN_DT_S = 1e-6
"""Two sightings closer in time than this are one instant (a disagreement, never a jump)."""
MAX_DISAGREEMENT_M = 0.01
"""Largest distance between corresponding world corners of one track seen by two views at one
instant: views labelled from one world box (a render) agree far closer, a wrong pose or a track id
given to two objects differ by far more."""
MAX_JUMP_SPEED_M_S = 40.0
"""Largest speed of a track's box centre between consecutive instants of one view."""


@dataclass(frozen=True)
class Sighting:
    """One tracked object in one frame, in the world: all the cross-frame checks need of a record
    (a validate run keeps these, not whole records, for every frame of a large dataset)."""

    frame_id: str
    sequence: str
    timestamp: float | None
    view: str
    track_id: int
    category: str
    corners: np.ndarray  # (8, 3) world corners, in the contract's order
    velocity: np.ndarray | None

    @property
    def instant(self) -> tuple[str, float] | None:
        return None if self.timestamp is None else instant_key(self.sequence, self.timestamp)


@dataclass(frozen=True)
class Disagreement:
    """One track at one instant placed apart by two views."""

    frame_a: str
    frame_b: str
    sequence: str
    timestamp: float
    track_id: int
    distance: float  # metres: the largest distance between corresponding world corners

    def __str__(self) -> str:
        return (f"track {self.track_id} of sequence {self.sequence} at t={self.timestamp:g} s: frames "
                f"{self.frame_a} and {self.frame_b} place it {self.distance:.3f} m apart")


@dataclass(frozen=True)
class Jump:
    """One track of one view moving implausibly fast between consecutive instants."""

    frame_a: str
    frame_b: str
    sequence: str
    view: str
    track_id: int
    speed: float  # m/s of the box centre between the two instants

    def __str__(self) -> str:
        return (f"track {self.track_id} of sequence {self.sequence} ({self.view}): moves at {self.speed:.1f} m/s "
                f"from frame {self.frame_a} to {self.frame_b}")


def instant_key(sequence: str, timestamp: float) -> tuple[str, float]:
    return sequence, round(float(timestamp), INSTANT_DECIMALS)


def world_boxes(record: FrameRecord) -> list[Box3D] | None:
    """Each object's box3d in the sequence's world (camera_to_world applied); None without a pose."""
    if record.camera_to_world is None:
        return None
    m = np.asarray(record.camera_to_world, dtype=np.float64)
    return [o.box.transformed(m[:3, :3], m[:3, 3]) for o in record.objects]


def sightings(record: FrameRecord) -> list[Sighting]:
    """The record's tracked objects in the world; none for a frame without sequence, pose or tracks."""
    boxes = world_boxes(record)
    if record.sequence is None or boxes is None:
        return []
    return [Sighting(record.frame_id, record.sequence, record.timestamp, record.view, o.track_id, o.category,
                     box.corners(), o.velocity)
            for o, box in zip(record.objects, boxes) if o.track_id is not None]


def _as_sightings(items: Iterable[FrameRecord | Sighting]) -> list[Sighting]:
    """Records expanded to their sightings; sightings kept (validate collects them as it reads)."""
    out: list[Sighting] = []
    for item in items:
        out.extend(sightings(item) if isinstance(item, FrameRecord) else [item])
    return out


def disagreements(records: Iterable[FrameRecord | Sighting]) -> list[Disagreement]:
    """Every pair of frames of one instant whose world boxes of one track differ by more than
    MAX_DISAGREEMENT_M."""
    by_track: dict[tuple, list[Sighting]] = defaultdict(list)
    for s in _as_sightings(records):
        if s.instant is not None:
            by_track[(*s.instant, s.track_id)].append(s)
    found = []
    for (sequence, timestamp, track), seen in sorted(by_track.items()):
        for a, b in combinations(seen, 2):
            distance = float(np.linalg.norm(a.corners - b.corners, axis=1).max())
            if distance > MAX_DISAGREEMENT_M:
                found.append(Disagreement(a.frame_id, b.frame_id, sequence, timestamp, track, distance))
    return found


def jumps(records: Iterable[FrameRecord | Sighting]) -> list[Jump]:
    """Every step of a track, within one view of its sequence, faster than MAX_JUMP_SPEED_M_S."""
    by_track: dict[tuple, list[Sighting]] = defaultdict(list)
    for s in _as_sightings(records):
        if s.timestamp is not None:
            by_track[(s.sequence, s.view, s.track_id)].append(s)
    found = []
    for (sequence, view, track), seen in sorted(by_track.items()):
        seen.sort(key=lambda s: s.timestamp)
        for a, b in zip(seen, seen[1:]):
            dt = b.timestamp - a.timestamp
            if dt < MIN_DT_S:
                continue
            speed = float(np.linalg.norm(b.corners.mean(axis=0) - a.corners.mean(axis=0))) / dt
            if speed > MAX_JUMP_SPEED_M_S:
                found.append(Jump(a.frame_id, b.frame_id, sequence, view, track, speed))
    return found


def shared_by_view_pair(records: Iterable[FrameRecord | Sighting]) -> dict[tuple[str, str], list[int]]:
    """For each pair of views (sorted labels), the number of tracks both saw at each instant where
    both were present with at least one track: how much cooperative views overlap."""
    tracks: dict[tuple, dict[str, set[int]]] = defaultdict(lambda: defaultdict(set))
    for s in _as_sightings(records):
        if s.instant is not None:
            tracks[s.instant][s.view].add(s.track_id)
    shared: dict[tuple[str, str], list[int]] = defaultdict(list)
    for instant in sorted(tracks):
        views = tracks[instant]
        for a, b in combinations(sorted(views), 2):
            shared[(a, b)].append(len(views[a] & views[b]))
    return dict(shared)
