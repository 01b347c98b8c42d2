"""Issue 7: rendering at scale. Shards (`--shard K/N`) and the Ray executor give the same dataset
as one unsharded local run: every record field, the raster images, depth and instance files, and
the manifest. A Ray worker killed in the middle of a frame loses no finished frame.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

from omnigen.cli import main
from omnigen.rigs.render import RenderJob, Renderer, parse_shard

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
pytest.importorskip("omnigen.scenes.raster_backend", reason="pyrender/PyOpenGL not installed")

W, H = 96, 64
FRAMES = 6
SEED = 3
RIG = "drone"
ARGS = ["--rig", RIG, "--frames", str(FRAMES), "--seed", str(SEED), "--scene", "tiny", "--width", str(W),
        "--height", str(H), "--backend", "raster"]
FILES = ("records", "images", "depth", "instance")


def _job(out: Path, **kw) -> RenderJob:
    return RenderJob(rig=RIG, frames=FRAMES, out=out, seed=SEED, scene="tiny", width=W, height=H, backend="raster", **kw)


@pytest.fixture(scope="module")
def reference(tmp_path_factory, headless_gl) -> Path:
    out = tmp_path_factory.mktemp("scale") / "one"
    assert main(["render", *ARGS, "--out", str(out)]) == 0
    return out


def assert_same_dataset(a: Path, b: Path) -> None:
    for sub in FILES:
        names = sorted(p.name for p in (a / sub).iterdir() if not p.name.startswith("."))
        assert names == sorted(p.name for p in (b / sub).iterdir() if not p.name.startswith(".")), sub
        assert len(names) == FRAMES
        for name in names:
            if sub == "records":  # every field (the bytes too: sorted keys, fixed float repr)
                assert json.loads((a / sub / name).read_text()) == json.loads((b / sub / name).read_text()), name
            assert (a / sub / name).read_bytes() == (b / sub / name).read_bytes(), (sub, name)
    assert (a / "manifest.json").read_bytes() == (b / "manifest.json").read_bytes()
    manifest = json.loads((b / "manifest.json").read_text())
    assert manifest["counts"]["frames"] == FRAMES and "shard" not in json.dumps(manifest)


def test_parse_shard_and_partition():
    assert parse_shard("2/3") == (2, 3)
    for bad in ("0/3", "4/3", "x", "1/0", "1-3"):
        with pytest.raises(ValueError):
            parse_shard(bad)
    for bad in (["--shard", "4/3"], ["--executor", "ray", "--retries", "-1"]):  # refused when parsed: usage, exit 2
        with pytest.raises(SystemExit) as refused:
            main(["render", *ARGS, "--out", "/nonexistent/x", *bad])
        assert refused.value.code == 2
    job = RenderJob(rig=RIG, frames=10, out=Path("/nonexistent"), start=5)
    parts = [RenderJob(rig=RIG, frames=10, out=Path("/x"), start=5, shard=(k, 3)).shard_indices() for k in (1, 2, 3)]
    assert sorted(sum(parts, [])) == list(job.indices())  # a partition: disjoint, complete
    assert parts[0] == [6, 9, 12] and all(i % 3 == 1 for i in parts[1])


def test_three_shards_sequential_equal_one_run(reference, tmp_path, capsys):
    out = tmp_path / "sharded"
    for k in (1, 2, 3):
        assert main(["render", *ARGS, "--out", str(out), "--shard", f"{k}/3"]) == 0
        if k < 3:  # the run is incomplete: no manifest yet, and --finalize-only refuses
            assert not (out / "manifest.json").exists()
            assert main(["render", *ARGS, "--out", str(out), "--finalize-only"]) == 1
            assert "not written yet" in capsys.readouterr().err
    assert_same_dataset(reference, out)
    # --finalize-only on a complete run rewrites the same manifest
    before = (out / "manifest.json").read_bytes()
    (out / "manifest.json").unlink()
    assert main(["render", *ARGS, "--out", str(out), "--finalize-only"]) == 0
    assert (out / "manifest.json").read_bytes() == before


def test_three_shards_concurrent_processes_equal_one_run(reference, tmp_path):
    out = tmp_path / "concurrent"
    exe = Path(sys.executable).parent / "omnigen"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-c", "import sys; from omnigen.cli import main; sys.exit(main())"]
    procs = [subprocess.Popen([*cmd, "render", *ARGS, "--out", str(out), "--shard", f"{k}/3"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for k in (1, 2, 3)]
    for p in procs:
        log, _ = p.communicate(timeout=240)
        assert p.returncode == 0, log
    assert_same_dataset(reference, out)
    assert not [p for p in out.rglob("*") if p.name.startswith(".tmp-")]


def test_shard_resume_skips_written_frames(reference, tmp_path):
    out = tmp_path / "resume"
    s = Renderer(_job(out, shard=(2, 2))).run(show_progress=False)
    assert (s.rendered, s.skipped, s.finalized) == (3, 0, False)
    s = Renderer(_job(out, shard=(2, 2))).run(show_progress=False)
    assert (s.rendered, s.skipped, s.finalized) == (0, 3, False)
    s = Renderer(_job(out)).run(show_progress=False)  # unsharded: renders only the rest, finalizes
    assert (s.rendered, s.skipped, s.finalized) == (3, 3, True)
    assert_same_dataset(reference, out)


# --- Ray -------------------------------------------------------------------------------------

needs_ray = pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                               reason="ray not installed (optional extra: pip install 'ray[default]')")


@pytest.fixture(scope="module")
def ray_local():
    ray = pytest.importorskip("ray", reason="ray not installed (optional extra: pip install 'ray[default]')")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, _temp_dir="/tmp/omnigen-ray-test",
             configure_logging=False)
    yield ray
    ray.shutdown()


@needs_ray
def test_ray_equals_local(reference, ray_local, tmp_path):
    out = tmp_path / "ray"
    # through the command line, on the Ray this process already runs: 2 actors, each restarted after 2 frames
    assert main(["render", *ARGS, "--out", str(out), "--executor", "ray", "--frames-per-worker", "2"]) == 0
    assert_same_dataset(reference, out)


@needs_ray
def test_ray_worker_killed_mid_frame_loses_nothing(reference, ray_local, tmp_path, monkeypatch):
    from omnigen.rigs.ray_executor import CRASH_ENV, run_ray

    out = tmp_path / "crash"
    marker = tmp_path / "crashed"
    monkeypatch.setenv(CRASH_ENV, f"3:{marker}")
    # the first shard (frames 0, 2, 4) on Ray first: those frames are finished before the crash
    first = run_ray(_job(out, shard=(1, 2)), show_progress=False)
    assert (first.rendered, first.finalized) == (3, False)
    done_before = {p.name: p.stat().st_mtime_ns for p in (out / "records").iterdir()}
    s = run_ray(_job(out), retries=2, show_progress=False)
    assert marker.exists()  # the actor rendering frame 3 died after its images, before its record
    assert (s.rendered, s.skipped, s.failed, s.finalized) == (3, 3, [], True)
    for name, mtime in done_before.items():  # finished frames were neither lost nor rendered again
        assert (out / "records" / name).stat().st_mtime_ns == mtime
    assert_same_dataset(reference, out)


@needs_ray
def test_ray_frame_failing_past_retries_is_reported(ray_local, tmp_path, monkeypatch):
    from omnigen.rigs.ray_executor import CRASH_ENV, run_ray

    out = tmp_path / "fail"
    monkeypatch.setenv(CRASH_ENV, f"1:{tmp_path / 'crashed'}")
    s = run_ray(RenderJob(rig=RIG, frames=2, out=out, seed=SEED, scene="tiny", width=W, height=H, backend="raster"),
                retries=0, show_progress=False)
    assert (s.rendered, s.failed, s.finalized) == (1, [1], False)
    assert not (out / "manifest.json").exists()
    monkeypatch.delenv(CRASH_ENV)
    s = run_ray(RenderJob(rig=RIG, frames=2, out=out, seed=SEED, scene="tiny", width=W, height=H, backend="raster"),
                show_progress=False)  # a rerun renders what failed
    assert (s.rendered, s.skipped, s.failed, s.finalized) == (1, 1, [], True)
