"""merge keeps a sequence (all its views) and a cooperative pair on one side of every split,
whatever groups their source drew (the fakes draw none: each frame alone)."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import replace

from omnigen.fakes import fake_cooperative_records, write_cooperative_dataset
from omnigen.merge import merge
from omnigen.splits import read_assignments


def sides(root, records, key) -> list[set[str]]:
    """The splits each value of `key` (a record attribute) landed in."""
    split = read_assignments(root)
    by_key = defaultdict(set)
    for r in records:
        if getattr(r, key) is not None:
            by_key[getattr(r, key)].add(split[r.frame_id])
    return list(by_key.values())


def test_a_sequence_never_straddles_splits(tmp_path):
    records = fake_cooperative_records(seed=4, n_sequences=8, n_instants=2, n_objects=2)
    write_cooperative_dataset(tmp_path / "coop", records)
    merge([tmp_path / "coop"], tmp_path / "uov", test_fraction=0.5, seed=1)
    by_sequence = sides(tmp_path / "uov", records, "sequence")
    assert len(by_sequence) == 8 and all(len(s) == 1 for s in by_sequence)
    assert set().union(*by_sequence) == {"train", "test"}  # a real split, not everything on one side


def test_a_pair_never_straddles_splits(tmp_path):
    """Pairs without sequences (a cooperative source that knows no runs): the pair alone joins."""
    records = [replace(r, sequence=None, timestamp=None)
               for r in fake_cooperative_records(seed=5, n_sequences=4, n_instants=4, n_objects=2)]
    write_cooperative_dataset(tmp_path / "coop", records)
    merge([tmp_path / "coop"], tmp_path / "uov", test_fraction=0.5, seed=2)
    by_pair = sides(tmp_path / "uov", records, "pair")
    assert len(by_pair) == 16 and all(len(s) == 1 for s in by_pair)
    assert set().union(*by_pair) == {"train", "test"}
