"""stats.json's `tracks` section: how long objects are followed, how fast they move and how much
cooperative views overlap, for datasets with sequences.

Built from the index's columns (no record is parsed again): each tracked object of a posed frame
becomes an omnigen.cooperation Sighting, the form the cross-frame checks read.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np

from omnigen.conventions import FINE_CLASSES
from omnigen.cooperation import Sighting, disagreements, jumps, shared_by_view_pair
from omnigen.dataset import Dataset
from omnigen.geometry import cuboid_corners
from omnigen.stats.compute import rnd, summary


def has_sequences(ds: Dataset) -> bool:
    return any(s is not None for s in ds.table.sequence)


def dataset_sightings(ds: Dataset) -> list[Sighting]:
    """Every tracked object of a frame with a sequence and a pose, its corners in the world."""
    ft, t = ds.table, ds.objects
    posed = np.array([s is not None for s in ft.sequence], dtype=bool) & ~np.isnan(ft.camera_to_world).any(axis=(1, 2))
    keep = np.flatnonzero(posed[t.frame] & (t.track_id >= 1))
    if len(keep) == 0:
        return []
    pose = ft.camera_to_world[t.frame[keep]]
    rotation = pose[:, :3, :3] @ t.rotation[keep]
    center = np.einsum("nij,nj->ni", pose[:, :3, :3], t.center[keep]) + pose[:, :3, 3]
    corners = cuboid_corners(center, t.dims[keep], rotation)
    out = []
    for k, j in enumerate(keep.tolist()):
        f = int(t.frame[j])
        ts = ft.timestamp[f]
        velocity = t.velocity[j]
        out.append(Sighting(ft.frame_id[f], ft.sequence[f], None if np.isnan(ts) else float(ts), ft.view[f],
                            int(t.track_id[j]), FINE_CLASSES[int(t.category[j])], corners[k],
                            None if np.isnan(velocity).any() else velocity))
    return out


def tracks_section(ds: Dataset) -> dict[str, Any]:
    """Per track (a sequence's track id): instants seen and seconds followed; speeds by class from
    the labelled velocities; tracks shared per view pair and instant; and the counts of the
    cross-frame problems `omnigen validate` lists one by one."""
    seen = dataset_sightings(ds)
    instants: dict[tuple[str, int], set[float]] = defaultdict(set)
    for s in seen:
        if s.instant is not None:
            instants[(s.sequence, s.track_id)].add(s.instant[1])
    per_track = list(instants.values())
    speeds: dict[str, list[float]] = defaultdict(list)
    for s in seen:
        if s.velocity is not None:
            speeds[s.category].append(float(np.linalg.norm(s.velocity)))
    shared = shared_by_view_pair(seen)
    return {
        "sequences": len({s for s in ds.table.sequence if s is not None}),
        "tracks": len(per_track),
        "instants_per_track": summary(np.array([len(v) for v in per_track], dtype=np.float64)),
        "seconds_per_track": summary(np.array([max(v) - min(v) for v in per_track], dtype=np.float64)),
        "speed_by_class": {c: summary(np.array(speeds[c])) for c in FINE_CLASSES if c in speeds},
        "shared_by_view_pair": {f"{a}+{b}": {"instants": len(n), "mean": rnd(float(np.mean(n))), "total": int(sum(n))}
                                for (a, b), n in sorted(shared.items())},
        "disagreements": len(disagreements(seen)),
        "jumps": len(jumps(seen)),
    }
