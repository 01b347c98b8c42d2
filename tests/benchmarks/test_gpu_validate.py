"""benchmarks/gpu_validate.py at tiny size on the CPU (so the GPU script cannot rot), its companions'
pieces: the wheel list against the imports, the EGL loaders' unpacking, and peer_ultralytics.py's
conversion of Ultralytics predictions and its exit where Ultralytics is missing."""

from __future__ import annotations

import ctypes
import io
import json
import re
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks import fetch_gpu_wheels, gpu_validate, peer_ultralytics  # noqa: E402

LAST_LINE = re.compile(r"^gpu_validate: synthetic mAP50:95 \d\.\d{3}, adherence (-|\d+\.\d{2}) deg, \d+\.\d img/s$")
TINY = ["--device", "cpu", "--frames", "4", "--cities", "2", "--city-frames", "1", "--test-fraction", "0.5",
        "--scene", "tiny", "--size", "128", "--batch", "4", "--minutes", "0.1", "--jobs", "2",
        "--workers", "0", "--train-args", "model.imgsz=64 optim.batch=4"]


@pytest.fixture(scope="module")
def egl(tmp_path_factory):
    """The raster backend's headless context, as the script's setup probes it; skip where there is none."""
    pytest.importorskip("omnigen.scenes.raster_backend", reason="pyrender/PyOpenGL not installed")
    env = gpu_validate.child_environment(tmp_path_factory.mktemp("site"))
    try:
        gpu_validate.egl_environment(env, tmp_path_factory.mktemp("gl"), None)
        return gpu_validate.gl_renderer(env)
    except SystemExit as exc:  # no headless GL: say so rather than fail obscurely
        pytest.skip(f"headless EGL rendering unavailable: {exc}")


def _run(work: Path, results: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(ROOT / "benchmarks" / "gpu_validate.py"), "--work", str(work), "--results", str(results),
           *TINY]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600)


def test_gpu_validate_runs_end_to_end_at_tiny_size_and_resumes(egl, tmp_path):
    results = tmp_path / "docs"
    results.mkdir()
    cpu = ROOT / "docs" / "results.json"
    if cpu.exists():  # make validate's figures: the section's CPU column
        shutil.copy(cpu, results / "results.json")
    (results / "RESULTS.md").write_text("# Results\n\nkept before\n\n<!-- gpu-validate: begin -->\nstale\n"
                                        "<!-- gpu-validate: end -->\n\n## Later\n\nkept after\n")
    work = tmp_path / "work"
    r = _run(work, results)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    last = r.stdout.strip().splitlines()[-1]
    assert LAST_LINE.match(last), last
    for stage in ("setup", "render", "data", "train", "eval"):
        assert re.search(rf"^gpu_validate: stage {stage} \d+\.\d s \(budget \d+ s\)$", r.stdout, re.M), stage

    out = json.loads((work / "results.json").read_text())
    kitti = 3 if gpu_validate.default_kitti() else 0
    assert out["frames"]["total"] == 3 * 4 + kitti and out["frames"]["by_source"]["synthetic"] == 12
    # make validate's split: one of each rig's two one-frame cities is tested, the extra city trained on
    assert out["frames"]["test"] >= 3 and out["frames"]["train"] >= 6
    assert set(out["stage_seconds"]) == {"setup", "render", "data", "train", "eval"}
    assert out["total_seconds"] == pytest.approx(sum(out["stage_seconds"].values()), abs=0.2)
    t = out["training"]
    assert t["epochs"] >= 1 and t["images"] == t["epochs"] * out["frames"]["train"] and t["images_per_s"] > 0
    assert out["synthetic"]["images"] >= 3 and 0.0 <= out["synthetic"]["oks_map50_95"] <= 1.0
    assert out["device"].startswith("CPU") and out["gl_renderer"] == egl
    assert json.loads((results / "gpu_results.json").read_text()) == out
    assert last == (f"gpu_validate: synthetic mAP50:95 {out['synthetic']['oks_map50_95']:.3f}, adherence "
                    + ("-" if out["synthetic"]["ground_adherence_deg"] is None
                       else f"{out['synthetic']['ground_adherence_deg']:.2f}") + f" deg, {t['images_per_s']:.1f} img/s")

    md = (results / "RESULTS.md").read_text()
    assert md.startswith("# Results\n\nkept before\n\n<!-- gpu-validate: begin -->\n## On one GPU")
    assert md.endswith("<!-- gpu-validate: end -->\n\n## Later\n\nkept after\n")
    assert "stale" not in md and md.count("<!-- gpu-validate: begin -->") == 1
    assert f"| OKS mAP50:95 | {out['synthetic']['oks_map50_95']:.3f} |" in md
    if cpu.exists():
        assert "| synthetic test split | this run | make validate (CPU) |" in md

    again = _run(work, results)  # resumes: every stage after the setup is done
    assert again.returncode == 0, again.stderr[-3000:]
    assert "[run] omnigen" not in again.stdout and again.stdout.count("(done earlier)") == 4
    resumed = json.loads((work / "results.json").read_text())["stage_seconds"]
    assert {k: v for k, v in resumed.items() if k != "setup"} == {k: v for k, v in out["stage_seconds"].items() if k != "setup"}


def test_the_wheel_list_covers_what_the_code_paths_import_and_nothing_more():
    try:  # the code paths import PyOpenGL on EGL, which loads the EGL library as it is imported
        ctypes.CDLL("libEGL.so.1")
    except OSError as exc:
        pytest.skip(f"no EGL library to import PyOpenGL on: {exc}")
    loaded = {fetch_gpu_wheels.canonical(d) for d in fetch_gpu_wheels.imported_distributions()}
    needs = {fetch_gpu_wheels.canonical(n.dist) for n in fetch_gpu_wheels.NEEDS}
    assert loaded - needs - fetch_gpu_wheels.IMAGE_HAS == set()  # nothing the GPU machine would lack
    assert needs - loaded == set()  # nothing carried that the code paths do not import
    assert needs.isdisjoint(fetch_gpu_wheels.IMAGE_HAS)


# Names numpy 2 removed (its migration guide, NPY201) and modules Python 3.12 removed: the GPU
# machine runs our code from the checkout on numpy 2 and Python 3.12, where none of them exists.
NUMPY1_ONLY = re.compile(r"\bnp\.(float_|complex_|infty|Inf|Infinity|NaN|NINF|PINF|NZERO|PZERO|string_|unicode_|"
                         r"int0|uint0|bool8|longfloat|longcomplex|clongfloat|cfloat|singlecomplex|product|cumproduct|"
                         r"alltrue|sometrue|row_stack|asfarray|find_common_type|cast|mat|round_|msort|trapz|in1d|"
                         r"issubclass_|maximum_sctype|obj2sctype|sctype2char|sctypes|issctype|set_string_function|"
                         r"safe_eval|recfromcsv|recfromtxt|deprecate|disp|who|byte_bounds|source|lookfor|DataSource)\b")
PY312_REMOVED = re.compile(r"^\s*(import|from)\s+(distutils|imp|asynchat|asyncore|smtpd)\b", re.M)


def test_our_code_names_nothing_numpy_2_or_python_3_12_removed():
    found = []
    for folder in ("omnigen", "rigs", "scenes", "detector", "converters", "benchmarks"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            text = path.read_text()
            found += [f"{path.relative_to(ROOT)}: {m.group(0)}" for m in NUMPY1_ONLY.finditer(text)]
            found += [f"{path.relative_to(ROOT)}: {m.group(0).strip()}" for m in PY312_REMOVED.finditer(text)]
    assert found == []


def test_what_a_machine_lacks_is_read_from_its_pip_freeze(tmp_path):
    freeze = tmp_path / "freeze.txt"
    freeze.write_text("numpy==2.1.0\nShapely==2.0.6\npyopengl==3.1.7\n# comment\n")
    lacks = {n.dist for n in fetch_gpu_wheels.missing_needs(fetch_gpu_wheels.read_have(freeze))}
    assert "shapely" not in lacks and "PyOpenGL" not in lacks and {"orjson", "pyrender"} <= lacks
    pins = fetch_gpu_wheels.pinned_versions()
    assert all(fetch_gpu_wheels.wanted_version(n.dist, pins) for n in fetch_gpu_wheels.NEEDS)
    assert fetch_gpu_wheels.wanted_version("PyOpenGL", pins) == "3.1.10"  # 3.1.0 has no wheel


def _deb(path: Path, files: dict[str, bytes], links: dict[str, str]) -> None:
    """A minimal Debian package: an ar archive with debian-binary, control and data members."""
    data = io.BytesIO()
    with tarfile.open(fileobj=data, mode="w:xz") as tar:
        for name, body in files.items():
            info = tarfile.TarInfo(f"./{name}")
            info.size = len(body)
            tar.addfile(info, io.BytesIO(body))
        for name, target in links.items():
            info = tarfile.TarInfo(f"./{name}")
            info.type, info.linkname = tarfile.SYMTYPE, target
            tar.addfile(info)
    blob = b"!<arch>\n"
    for name, body in (("debian-binary", b"2.0\n"), ("control.tar.xz", b"x"), ("data.tar.xz", data.getvalue())):
        blob += f"{name:<16}{0:<12}{0:<6}{0:<6}{100644:<8}{len(body):<10}`\n".encode() + body + b"\n" * (len(body) % 2)
    path.write_bytes(blob)


def test_egl_loaders_are_unpacked_and_put_on_the_library_path_when_the_machine_lacks_them(tmp_path, monkeypatch):
    wheels = tmp_path / "wheels"
    (wheels / "debs").mkdir(parents=True)
    lib = "usr/lib/x86_64-linux-gnu"
    _deb(wheels / "debs" / "libegl1_1.6.0-1_amd64.deb", {f"{lib}/libEGL.so.1.1.0": b"\x7fELF"},
         {f"{lib}/libEGL.so.1": "libEGL.so.1.1.0"})
    monkeypatch.setattr(gpu_validate, "can_load", lambda library, env: False)
    env = {"LD_LIBRARY_PATH": "/opt/x"}
    notes = gpu_validate.egl_environment(env, tmp_path / "work", wheels)
    unpacked = tmp_path / "work" / "gl" / lib
    assert (unpacked / "libEGL.so.1").resolve() == (unpacked / "libEGL.so.1.1.0").resolve()
    assert env["LD_LIBRARY_PATH"].split(":")[0] == str(unpacked) and env["LD_LIBRARY_PATH"].endswith(":/opt/x")
    assert env["PYOPENGL_PLATFORM"] == "egl" and any("unpacked" in n for n in notes)
    with pytest.raises(SystemExit, match="debs/"):
        gpu_validate.egl_environment({}, tmp_path / "work2", tmp_path / "empty")


def test_missing_packages_without_wheels_are_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setattr(gpu_validate, "missing_modules", lambda: ["pyrender", "orjson"])
    with pytest.raises(SystemExit, match=r"pyrender, orjson cannot be imported.*fetch_gpu_wheels\.py"):
        gpu_validate.install_missing(None, tmp_path / "site")


def test_peer_exits_cleanly_where_ultralytics_is_missing(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ultralytics", None)  # import ultralytics -> ImportError
    assert peer_ultralytics.main(["--work", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("peer_ultralytics: ultralytics cannot be imported here")


def _fake_result(path: Path, labels: np.ndarray, width: int, height: int) -> SimpleNamespace:
    """What Ultralytics' pose predictor returns for an image, made from its YOLO label rows: a
    perfect prediction, in Ultralytics' pixels (measured from the image's corner)."""
    scale = np.array([width, height])
    cxcy, wh = labels[:, 1:3] * scale, labels[:, 3:5] * scale
    kp = labels[:, 5:].reshape(len(labels), -1, 3).copy()
    kp[..., :2] *= scale
    return SimpleNamespace(path=str(path), boxes=SimpleNamespace(
        xyxy=np.hstack([cxcy - wh / 2, cxcy + wh / 2]), conf=np.ones(len(labels)), cls=labels[:, 0]),
        keypoints=SimpleNamespace(data=kp))


def test_ultralytics_predictions_become_our_coco_results_exactly(tmp_path):
    from omnigen.detector.evaluation.oks_eval import evaluate
    from omnigen.dataset import Dataset
    from omnigen.fakes import write_fake_dataset
    from omnigen.splits import write_split
    from omnigen.formats.yolo import export_yolo

    ds = write_fake_dataset(tmp_path / "uov", n_frames=4, seed=2)
    write_split(ds.root, "test", ds.frame_ids[:2])
    export_yolo(ds, tmp_path / "yolo")
    ds = Dataset.open(ds.root, show_progress=False)
    fakes = []
    for label in sorted((tmp_path / "yolo" / "labels" / "test").glob("*.txt")):
        i = ds.index_of(label.stem)
        rows = np.loadtxt(label, ndmin=2)
        fakes.append(_fake_result(tmp_path / "yolo" / "images" / "test" / f"{label.stem}.png", rows,
                                  int(ds.table.width[i]), int(ds.table.height[i])))
    preds = peer_ultralytics.coco_predictions(fakes, {f: ds.index_of(f) for f in ds.frame_ids[:2]})
    o = ds.objects
    truth = [j for j in range(len(o)) if ds.table.frame_id[o.frame[j]] in ds.frame_ids[:2]]
    assert len(preds) == len(truth) > 0
    for p, j in zip(preds, truth):  # label files keep the dataset's object order
        assert p["frame_id"] == ds.table.frame_id[o.frame[j]] and p["image_id"] == o.frame[j] + 1
        kp = np.asarray(p["keypoints"]).reshape(-1, 3)
        on = kp[:, 2] > 0
        # the half-pixel shift undone: corners land on the dataset's own (to the labels' 6 decimals)
        np.testing.assert_allclose(kp[on, :2], o.keypoints[j][on], atol=1e-5 * max(ds.table.width))
    report = evaluate(ds, preds, split="test", adherence=False, sizes=False)
    assert report.rows[0].oks_map50_95 > 0.99


def test_make_validate_keeps_the_gpu_section_when_it_rewrites_results_md():
    from benchmarks.common import kept_sections, with_section

    old = with_section("# Results\n\nCPU tables\n", "gpu-validate", "## On one GPU\n\nfigures\n")
    assert old == "# Results\n\nCPU tables\n\n<!-- gpu-validate: begin -->\n## On one GPU\n\nfigures\n<!-- gpu-validate: end -->\n"
    rewritten = "# Results\n\nnew CPU tables\n" + kept_sections(old)  # what validate.py writes
    assert rewritten.endswith("\n\n<!-- gpu-validate: begin -->\n## On one GPU\n\nfigures\n<!-- gpu-validate: end -->\n")
    assert with_section(rewritten, "gpu-validate", "## On one GPU\n\nnew figures") == \
        rewritten.replace("\nfigures\n", "\nnew figures\n")
    assert kept_sections("# Results\n\nno sections\n") == ""


def test_training_takes_recipe_keys_and_renders_make_validates_mix():
    """--train-args' KEY=VALUE reach `omnigen train` right after the dataset (a recipe from
    bench_learning tried on the GPU), and the default scene is make validate's preset mix, kept in
    one place."""
    import argparse
    from pathlib import Path

    from benchmarks import gpu_validate
    from benchmarks.validate import SCENE_MIX

    args = argparse.Namespace(minutes=5.0, workers=2, seed=0, val_every=10, device="cuda",
                              train_args="model.kpt_mode=anchor loss.kpt_l1=1")
    argv = gpu_validate.train_arguments(Path("uov"), Path("run"), args)
    assert argv[:4] == ["train", "uov", "model.kpt_mode=anchor", "loss.kpt_l1=1"] and argv[4] == "--out"
    assert gpu_validate.trained_recipe(args).loss.kpt_l1 == 1.0
    assert gpu_validate.parse_args(["--work", "w"]).scene == SCENE_MIX


def test_the_gpu_recipe_is_make_validates():
    """The GPU run trains `omnigen train`'s own recipe, as make validate does: what train resolves
    from either script's command line is the validated recipe, so one kept change reaches both."""
    from dataclasses import asdict
    from pathlib import Path

    from benchmarks import validate
    from omnigen.cli import build_parser
    from omnigen.detector.train_command import config_of
    from omnigen.detector.recipe import RECIPE, recipe_of

    args = gpu_validate.parse_args(["--work", "w", "--device", "cuda"])
    gpu = gpu_validate.train_arguments(Path("uov"), Path("run"), args)
    assert gpu[:3] == ["train", "uov", "--out"] and not any("=" in a for a in gpu)
    v = validate.build_parser().parse_args([])
    v.amp = "bf16"
    cpu = validate.train_command(v, Path("uov"), Path("run"))
    resolved = [recipe_of(asdict(config_of(build_parser().parse_args(argv)))) for argv in (gpu, cpu)]
    assert resolved == [RECIPE, RECIPE] and gpu_validate.trained_recipe(args) == RECIPE
