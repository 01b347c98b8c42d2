"""The test split holds frames of every source that can be split (issue 45): two rendered cities
and KITTI put both sources in the test split, and the share reached per source is reported."""

from __future__ import annotations

import re

from omnigen.splits import assign_test_split, split_shares


def _cities_and_kitti(cities: int, kitti: int) -> tuple[dict[str, str], dict[str, str]]:
    """`cities` rendered cities seen by three rigs (5 frames each, one group a city) and `kitti`
    KITTI frames (one group each)."""
    groups, strata = {}, {}
    for c in range(cities):
        for view in ("ego", "infrastructure", "aerial"):
            for i in range(5):
                f = f"synthetic-{view}-s{c}-{i:06d}"
                groups[f], strata[f] = f"synthetic:city{c}", f"synthetic/{view}"
    for i in range(kitti):
        f = f"kitti-{i:06d}"
        groups[f], strata[f] = f, "kitti/ego"
    return groups, strata


def test_two_cities_and_kitti_put_both_sources_in_the_test_split():
    groups, strata = _cities_and_kitti(2, 3)
    for seed in range(5):
        a = assign_test_split(groups, strata, 0.25, seed)
        shares = {s.source: s for s in split_shares(groups, strata, a)}
        assert shares["synthetic"].test > 0 and shares["kitti"].test > 0, seed
        # a city stays whole and the other one trains
        cities = {groups[f]: a[f] for f in a if f.startswith("synthetic")}
        assert sorted(cities.values()) == ["test", "train"]


def test_a_source_of_one_group_is_reported_not_split():
    groups, strata = _cities_and_kitti(1, 8)
    a = assign_test_split(groups, strata, 0.25, 0)
    shares = {s.source: s for s in split_shares(groups, strata, a)}
    assert shares["synthetic"].groups == 1 and shares["synthetic"].test == 0
    assert shares["kitti"].test == 2 and shares["kitti"].share == 0.25


def test_no_test_fraction_no_test_frames():
    groups, strata = _cities_and_kitti(2, 3)
    assert set(assign_test_split(groups, strata, 0.0, 0).values()) == {"train"}


def test_merge_of_two_cities_and_kitti_tests_both_and_prints_each_share(tmp_path, capsys, monkeypatch):
    from omnigen import progress
    from omnigen.cli import main
    from omnigen.fakes import write_fake_dataset
    from omnigen.splits import read_split

    monkeypatch.setattr(progress.console, "width", 120)
    write_fake_dataset(tmp_path / "cities", 20)  # two groups of ten frames: two cities, each seen by every view
    write_fake_dataset(tmp_path / "kitti", 30, source="kitti")
    write_fake_dataset(tmp_path / "one-city", 10, seed=1, source="dair-v2x-i")  # one group only
    assert main(["merge", str(tmp_path / "cities"), str(tmp_path / "kitti"), str(tmp_path / "one-city"),
                 "--out", str(tmp_path / "uov"), "--test-fraction", "0.25"]) == 0
    out = capsys.readouterr().out
    test = read_split(tmp_path / "uov", "test")
    assert any(f.startswith("synthetic-") for f in test) and any(f.startswith("kitti-") for f in test)
    assert re.search(r"synthetic\s+│\s+20\s+│\s+10\s+│\s+0\.50\s+│\s+2", out), out
    assert "dair-v2x-i: no test frames: its 10 frames are one group" in out
    assert "render another city" in out
