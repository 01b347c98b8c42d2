"""Splits: which frames a model trains on and which it is tested on.

On disk a split is `splits/<name>.txt`, one frame id per line (as KITTI's ImageSets), so any tool
can read it. `assign_test_split` draws the held-out set: deterministic for a seed, stratified by
source and view, and never cutting a group, so near-duplicate frames (one city seed, one
DAIR-V2X sequence, frames sharing an image) all fall on the same side.
"""

from __future__ import annotations

import hashlib
import os
from collections import Counter, defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping

from omnigen.dataset import DatasetError
from omnigen.files import atomic_write_bytes

SPLITS_DIR = "splits"
TRAIN, TEST = "train", "test"


def split_names(root: str | os.PathLike) -> list[str]:
    """Names of the splits a dataset defines."""
    folder = Path(root) / SPLITS_DIR
    return sorted(p.stem for p in folder.glob("*.txt")) if folder.is_dir() else []


def read_split(root: str | os.PathLike, name: str) -> list[str]:
    """Frame ids of split `name`; an unknown split is an error listing the known ones."""
    path = Path(root) / SPLITS_DIR / f"{name}.txt"
    if not path.exists():
        known = split_names(root)
        raise DatasetError(f"{root}: no split {name!r} (known: {', '.join(known) or 'none'}; "
                           f"splits are written by 'omnigen merge')")
    return read_id_list(path)


def read_id_list(path: str | os.PathLike) -> list[str]:
    return [line.strip() for line in Path(path).read_text().splitlines() if line.strip()]


def write_split(root: str | os.PathLike, name: str, frame_ids: Iterable[str]) -> None:
    atomic_write_bytes(Path(root) / SPLITS_DIR / f"{name}.txt", "".join(f"{f}\n" for f in sorted(frame_ids)).encode())


def read_assignments(root: str | os.PathLike) -> dict[str, str]:
    """frame id -> split name, from every split file of a dataset."""
    out: dict[str, str] = {}
    for name in split_names(root):
        for frame_id in read_split(root, name):
            out[frame_id] = name
    return out


def _rank(seed: int, group: str) -> str:
    """A seed-dependent but machine-independent order of groups (no Python hash randomisation)."""
    return hashlib.sha256(f"{seed}\0{group}".encode()).hexdigest()


def assign_test_split(
    groups: Mapping[str, str],
    strata: Mapping[str, str],
    fraction: float,
    seed: int,
    fixed: Mapping[str, str] | None = None,
) -> dict[str, str]:
    """frame id -> TRAIN or TEST.

    groups: frame id -> group key (frames of one group share a side); strata: frame id -> stratum
    (e.g. "kitti/ego"); fixed: assignments to keep (from a split file or an earlier merge); a group
    with any fixed frame follows it. Free groups are visited in seeded-hash order and each joins the
    test set when that brings the test frames of the strata it touches closer to
    round(fraction * stratum size). With a fraction above 0, every source with two or more groups
    has test frames (`_hold_out_each_source`), and with two or more groups in all the test set
    holds at least one group.
    """
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"--test-fraction must be in [0, 1), got {fraction}")
    fixed = dict(fixed or {})
    members: dict[str, list[str]] = defaultdict(list)
    for frame_id, g in groups.items():
        members[g].append(frame_id)
    total: Counter[str] = Counter(strata.values())
    target = {s: round(fraction * n) for s, n in total.items()}
    in_test: Counter[str] = Counter()
    out: dict[str, str] = {}
    free: list[str] = []
    for g, frames in members.items():
        pinned = [fixed[f] for f in frames if f in fixed]
        if not pinned:
            free.append(g)
            continue
        if len(set(pinned)) > 1:  # one side each, or a scene (or an image) would sit in two splits
            a = next(f for f in frames if f in fixed)
            b = next(f for f in frames if f in fixed and fixed[f] != fixed[a])
            raise ValueError(f"frames {a} ({fixed[a]}) and {b} ({fixed[b]}) are one group (one scene, or the "
                             "same pixels) but are pinned to different splits (by split files, or by an "
                             "earlier merge under --update); a group keeps to one split")
        side = pinned[0]
        for f in frames:
            out[f] = fixed.get(f, side)
            in_test[strata[f]] += out[f] == TEST
    for g in sorted(free, key=lambda g: _rank(seed, g)):
        adds = Counter(strata[f] for f in members[g])
        # Take the group when it brings the test set closer to every stratum's target (squared
        # error): groups that span strata (one city seen by three rigs) are weighed as a whole.
        before = sum((target[s] - in_test[s]) ** 2 for s in adds)
        after = sum((target[s] - in_test[s] - n) ** 2 for s, n in adds.items())
        side = TEST if after < before else TRAIN
        for f in members[g]:
            out[f] = side
        if side == TEST:
            in_test.update(adds)
    if fraction > 0:
        _hold_out_each_source(members, strata, out, free, seed)
    if fraction > 0 and free and len(members) >= 2 and TEST not in out.values():
        # Groups larger than the whole target (19 frames in groups of 10 at 0.1) would leave no
        # test split at all, and `export --split test` would then fail: with two or more groups
        # the smallest free one is held out (the seeded order breaks ties), the rest train.
        g = min(free, key=lambda g: (len(members[g]), _rank(seed, g)))
        for f in members[g]:
            out[f] = TEST
    return out


def source_of(stratum: str) -> str:
    """The source part of a stratum ("kitti/ego" -> "kitti")."""
    return stratum.partition("/")[0]


def _hold_out_each_source(members: Mapping[str, list[str]], strata: Mapping[str, str], out: dict[str, str],
                          free: list[str], seed: int) -> None:
    """Give every source of two or more groups at least one test group, in place.

    The squared-error draw weighs a group as a whole, so a source made of a few large groups (two
    rendered cities, each seen by three rigs) never finds one that brings its strata closer to
    their targets, and the test set held no frame of it: its evaluation scored nothing rendered.
    Such a source gets its smallest free group (the seeded order breaks ties) while another of its
    groups stays in training; a source of one group cannot be split without leaking it, and
    `split_shares` names it instead.
    """
    groups_of: dict[str, set[str]] = defaultdict(set)
    for g, frames in members.items():
        for f in frames:
            groups_of[source_of(strata[f])].add(g)
    free_set = set(free)
    for source in sorted(groups_of):
        mine = groups_of[source]
        if len(mine) < 2 or any(out[f] == TEST for g in mine for f in members[g] if source_of(strata[f]) == source):
            continue
        movable = [g for g in mine if g in free_set and out[members[g][0]] == TRAIN]
        if not movable:
            continue
        g = min(movable, key=lambda g: (len(members[g]), _rank(seed, g)))
        if all(out[members[h][0]] == TEST or h == g for h in mine):
            continue  # taking it would leave the source no training group
        for f in members[g]:
            out[f] = TEST


@dataclass(frozen=True)
class SourceShare:
    """How much of one source the test split holds, and how many groups it could be cut from."""

    source: str
    test: int
    frames: int
    groups: int

    @property
    def share(self) -> float:
        return self.test / self.frames if self.frames else 0.0


def split_shares(groups: Mapping[str, str], strata: Mapping[str, str], assignment: Mapping[str, str]
                 ) -> list[SourceShare]:
    """Per source: test frames, frames and groups, in source order: what merge prints, so that a
    share far from the one asked for (whole groups) and a source of one group are seen at once."""
    frames: Counter[str] = Counter()
    test: Counter[str] = Counter()
    group_sets: dict[str, set[str]] = defaultdict(set)
    for f, stratum in strata.items():
        source = source_of(stratum)
        frames[source] += 1
        test[source] += assignment.get(f) == TEST
        group_sets[source].add(groups.get(f, f))
    return [SourceShare(s, test[s], frames[s], len(group_sets[s])) for s in sorted(frames)]
