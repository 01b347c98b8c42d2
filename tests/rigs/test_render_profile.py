"""`bench_render.py --profile` (issue 48): where a frame's time goes, a stage root split by the
functions it calls, from cProfile's call graph."""

from __future__ import annotations

import cProfile
import itertools
import pstats

import pytest

from benchmarks.bench_render import PROFILE_ROOTS, call_tree, profile_frames, profile_rows


def _leaf() -> None:
    pass


def _work(n: int) -> None:
    for _ in range(n):  # the deterministic clock below counts events: cost grows with the calls made
        _leaf()


def _shared(n: int) -> None:
    _work(n)


def _heavy() -> None:
    _shared(30)
    [_work(20) for _ in range(3)]  # a comprehension: looked through
    [].extend(_work(10) for _ in range(2))  # a builtin that only drives a generator: looked through too


def _light() -> None:
    _shared(10)
    _work(0)  # under the share shown: folded into "other"


def root() -> None:
    _heavy()
    _light()


def _stats() -> pstats.Stats:
    ticks = itertools.count()
    prof = cProfile.Profile(lambda: next(ticks))  # one tick an event: the same figures on any machine
    prof.enable()
    root()
    prof.disable()
    return pstats.Stats(prof)


def _func(stats: pstats.Stats, name: str):
    return next(f for f in stats.stats if f[2] == name and f[0].endswith("test_render_profile.py"))


def test_call_tree_splits_a_root_by_its_callees():
    stats = _stats()
    tree = call_tree(stats, "test_render_profile.py", "root", 3, frames=2)
    top = ("test_render_profile.root",)
    assert set(tree) >= {top, top + ("_heavy",), top + ("_light",), top + ("_heavy", "_work"), top + ("_heavy", "_shared")}
    assert tree[top][1] == 0.5  # calls per frame: one call over two frames
    assert tree[top + ("_heavy", "_work")][1] == 2.5  # five calls from the comprehensions, counted as _heavy's
    assert not any("listcomp" in part or "extend" in part for path in tree for part in path)
    # _shared is called from _heavy and _light: its callees go to each in proportion to its time there
    shared, work = _func(stats, "_shared"), _func(stats, "_work")
    table = stats.stats
    from_heavy = table[shared][4][_func(stats, "_heavy")][3] / table[shared][3]
    assert from_heavy == pytest.approx(31 / 42, abs=0.05)  # _shared(30) against _shared(10)
    assert tree[top + ("_heavy", "_shared", "_work")][0] == pytest.approx(from_heavy * table[work][4][shared][3] / 2)
    assert tree[top + ("_light", "_shared", "_work")][0] == pytest.approx((1 - from_heavy) * table[work][4][shared][3] / 2)
    # children never add up to more than their parent
    for path, (sec, _) in tree.items():
        kids = [s for p, (s, _) in tree.items() if len(p) == len(path) + 1 and p[:-1] == path]
        assert sum(kids) <= sec + 1e-9


def test_a_small_callee_is_folded_into_other():
    tree = call_tree(_stats(), "test_render_profile.py", "root", 3, frames=1)
    light = ("test_render_profile.root", "_light")
    assert light + ("_shared",) in tree
    assert light + ("_work",) not in tree  # _work(1) costs a few events, under PROFILE_MIN_SHARE of root
    assert call_tree(_stats(), "test_render_profile.py", "absent", 3, frames=1) == {}


@pytest.mark.usefixtures("headless_gl")
def test_profile_rows_name_the_parts_of_a_raster_frame():
    results = {"tiny": profile_frames("raster", "tiny", 2, 48, "preview", clock="cpu")}
    rows = profile_rows(results, 2)
    labels = [r[0].strip() for r in rows]
    for label, *_ in PROFILE_ROOTS:
        assert label in labels
    assert "placement.place_world" in labels and "stage scene (wall)" in labels
    assert all(len(r) == 2 for r in rows)


@pytest.mark.usefixtures("headless_gl")
def test_profile_ahead_draws_the_scenes_in_the_second_process():
    """--profile-ahead: the frames after frame 0 are drawn by the worker, so the render process's
    profile holds no scene drawing (without it, one a frame)."""
    def drawn(stats: pstats.Stats) -> int:
        return sum(v[1] for f, v in stats.stats.items() if f[2] == "randomize_frame")

    assert drawn(profile_frames("raster", "tiny", 3, 48, "preview", clock="cpu")[0]) == 2
    assert drawn(profile_frames("raster", "tiny", 3, 48, "preview", clock="cpu", ahead=True)[0]) == 0


def test_one_run_measures_memory_for_each_backend_named(monkeypatch):
    """The issue's figures come from one run: --memory-backend raster,cycles runs each long run in turn."""
    import sys

    import benchmarks.bench_render as bench

    ran = []
    monkeypatch.setattr(bench, "memory", lambda backend, *rest, **kw: ran.append(backend))
    monkeypatch.setattr(sys, "argv", ["bench_render.py", "--no-raster", "--no-cycles", "--memory-frames", "20",
                                      "--memory-backend", "raster,cycles"])
    assert bench.main() == 0 and ran == ["raster", "cycles"]
    with pytest.raises(Exception):
        bench.backends("raster,gl")
