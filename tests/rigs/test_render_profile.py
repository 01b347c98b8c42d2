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


@pytest.mark.usefixtures("headless_gl")
def test_coop_prints_the_ratio_stages_share_and_memory(monkeypatch, capsys):
    """--coop (issue 46): a cooperative raster sequence against as many drone frames in one run,
    and with --memory-instants the long cooperative run's resident memory by instant."""
    import re
    import sys

    import benchmarks.bench_render as bench

    monkeypatch.setattr(sys, "argv", ["bench_render.py", "--coop", "2", "--size", "32", "--scene", "intersection",
                                      "--memory-instants", "3", "--memory-every", "1", "--memory-size", "32"])
    monkeypatch.setattr(bench, "rss_mb", lambda: 1072.0)  # printed with a thousands separator, as a long run's is
    assert bench.main() == 0
    out = capsys.readouterr().out
    assert "ego,pole,drone" in out
    assert re.search(r"view-frames timed, each\s*│\s*6 ", out)  # 2 instants x 3 views, and 6 drone frames
    for row in ("cooperative, s per view-frame", "single rig (drone), s per view-frame",
                "ratio cooperative / single (target <= 1.2)", "share seen by 2+ views", "city + backend build, s"):
        assert row in out, row
    for stage in bench.COOP_STAGES:
        assert f"stage {stage}, s per view-frame (coop / single)" in out
    ratio = float(re.search(r"ratio cooperative / single \(target <= 1\.2\)\s*│\s*([\d.]+)", out).group(1))
    assert ratio > 0
    readings = re.findall(r"^\s*(\d+)\s*│\s*[\d,]+\s*│\s*\d+\s*$", out.split("resident MB by instant")[1], re.M)  # 1,072 MB
    assert readings == ["1", "2", "3"]
    assert re.search(r"after instant 1 \d+, after instant 3 \d+: [+-]\d+\.\d% \(target within 10%\)", out)


def test_shared_share_counts_a_track_once_per_view_and_instant():
    from types import SimpleNamespace as NS

    from benchmarks.bench_render import shared_share

    def rec(t, *tracks):
        return NS(sequence="q", timestamp=t, objects=[NS(track_id=k) for k in tracks])

    # instant 0: track 1 in two views, 2 in one (twice in one view: still one), None never counted; instant 0.1: 1 alone
    records = [rec(0.0, 1, 2, 2, None), rec(0.0, 1), rec(0.1, 1)]
    assert shared_share(records) == (pytest.approx(1 / 3), 3)
    assert shared_share([]) == (0.0, 0)


@pytest.mark.parametrize("argv", [["--coop", "3", "--coop-length", "2"], ["--coop", "2", "--coop-length", "0"],
                                  ["--coop", "2", "--coop-length", "2", "--memory-instants", "3"],
                                  ["--coop", "2", "--memory-every", "0"]])
def test_coop_refuses_bad_counts_in_one_line(monkeypatch, capsys, argv):
    import sys

    import benchmarks.bench_render as bench

    monkeypatch.setattr(sys, "argv", ["bench_render.py", *argv])
    for ran in ("coop", "bench", "memory"):
        monkeypatch.setattr(bench, ran, lambda *a, **k: pytest.fail("ran despite bad counts"))
    with pytest.raises(SystemExit):
        bench.main()
    assert len([line for line in capsys.readouterr().err.splitlines() if "error" in line]) == 1


@pytest.mark.parametrize("argv, flag", [(["--coop", "5", "--coop-length", "2"], "--coop 5"),
                                        (["--coop", "4", "--coop-length", "2", "--memory-instants", "3"],
                                         "--memory-instants 3")])
def test_a_cooperative_run_of_part_sequences_is_refused_before_any_render(monkeypatch, capsys, argv, flag):
    import sys

    import benchmarks.bench_render as bench

    def never(*a, **k):
        raise AssertionError("rendered before the arguments were checked")

    monkeypatch.setattr(bench, "coop", never)
    monkeypatch.setattr(bench, "coop_memory", never)
    monkeypatch.setattr(sys, "argv", ["bench_render.py", *argv])
    with pytest.raises(SystemExit):
        bench.main()
    err = capsys.readouterr().err
    assert flag in err and "multiple of the sequence length" in err


def test_whole_sequences_is_the_functions_own_check_too():
    from benchmarks.bench_render import coop, coop_memory

    with pytest.raises(ValueError, match="--coop 3 must be a positive multiple"):
        coop(3, 2, 32, "tiny", 0)
    with pytest.raises(ValueError, match="--memory-instants 0 must be a positive multiple"):
        coop_memory(0, 1, 32, "tiny", 0)
