"""A time-boxed run on one GPU machine: render, train nano+P2 with `--time`, evaluate; results.json and a RESULTS.md section.

    python3 benchmarks/gpu_validate.py --work /tmp/gv --wheels /path/to/gpu-wheels    # docs/gpu.md
    .venv/bin/python benchmarks/gpu_validate.py --work runs/gv --device cpu --frames 6 --cities 2 \\
        --city-frames 2 --scene tiny --size 128 --batch 4 --minutes 0.1 --results /tmp/r \\
        --train-args "model.imgsz=64 optim.batch=4"                                           # the tiny test

For a fresh single-GPU Linux x86_64 machine without network that has Python 3.12, PyTorch with CUDA,
numpy 2 and OpenCV and nothing of ours: the code runs from this checkout through sys.path (and
PYTHONPATH for the processes it starts), because our pyproject pins what such a machine does not
have (Python 3.11, numpy<2, a CPU torch). This module imports only the standard library until the
setup stage has made the rest importable: the distributions it cannot import are installed from
--wheels (benchmarks/fetch_gpu_wheels.py fetches them) with `pip install --no-index --no-deps
--target WORK/site`; a folder beside the interpreter rather than into it, since there the
interpreter is itself a venv whose own venvs would not see its torch.

Stages, each timed and printed against its share of the 12 minutes (a stage whose output exists is
skipped, so an interrupted run resumes; benchmarks/common.py's Runner and train_stage, as validate.py):
- setup: the wheels; EGL (glvnd's loaders from WORK/gl when the machine lacks libEGL.so.1, the
  NVIDIA driver's vendor file when it is out of glvnd's sight); a child process that makes the
  raster backend's context and says which GL renderer it got.
- render: --jobs `omnigen render --backend raster` processes at once, each rig's --cities cities of
  --city-frames frames exactly as `make validate` renders them (so its test split is the same:
  the GPU's figures stand beside the CPU's on the same frames), plus the rest of --frames per rig
  from more cities, for training only.
- data: KITTI converted; the `make validate` renders merged with it to draw the test split, then
  everything merged with that split pinned (`--split-file`, the rest train).
- train: `omnigen train --time --minutes`, the recipe as make validate trains it (detector/recipe.py:
  nano+P2, its windows, its crop stage's second phase; --train-args changes keys), both phases fitted
  to the budget, --cache, amp auto.
- eval: `omnigen eval last.pt --baseline` on the test split (the corner errors beside the
  box-template baseline's, docs/metric-3d.md).
- --peer: benchmarks/peer_ultralytics.py on the same data for the same minutes (outside the budget).
Writes WORK/results.json, and into --results: the `gpu-validate` section of RESULTS.md (the rest of
the file kept) and gpu_results.json. The last line printed is
`gpu_validate: synthetic mAP50:95 X, adherence Y deg, Z img/s`.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import importlib
import importlib.util
import io
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import tarfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import (NEEDS, SCENE_MIX, Runner, check_data_arguments, fmt, machine, metric_row,  # noqa: E402
                               render_jobs, run_renders, synthetic_row, train_stage, usable_cores, use_site,
                               with_section)  # the standard library alone until a stage's function runs

BUDGET_SECONDS = 12 * 60
SECTION = "gpu-validate"
# What a stage may take of the 12 minutes; train's is --minutes plus its start and last checkpoint.
STAGE_BUDGETS = {"setup": 30.0, "render": 120.0, "data": 15.0, "eval": 60.0}
NVIDIA_EGL_VENDOR = Path("/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json")
GLVND_VENDOR_DIRS = (Path("/usr/share/glvnd/egl_vendor.d"), Path("/etc/glvnd/egl_vendor.d"))
# glvnd's loaders unpack under this, as the Debian packages lay them out
DEB_LIBDIR = Path("usr/lib/x86_64-linux-gnu")
# enough for nano+P2 on an H100 in 7 minutes, far under what fits: `--epochs` bounds a `--time` run
MAX_EPOCHS = 2000


# ---------------------------------------------------------------------------------------------
# setup: packages, EGL, the GL probe (standard library only until install_missing has run)
# ---------------------------------------------------------------------------------------------


def missing_modules() -> list[str]:
    """The needed distributions (fetch_gpu_wheels.NEEDS) whose module this process cannot import."""
    return [n.dist for n in NEEDS if importlib.util.find_spec(n.module) is None]


def install_missing(wheels: Path | None, site: Path) -> list[str]:
    """Install what is missing from `wheels` into `site`; returns what was installed."""
    use_site(site)
    missing = missing_modules()
    if not missing:
        return []
    if wheels is None or not wheels.is_dir():
        raise SystemExit(f"gpu_validate: {', '.join(missing)} cannot be imported here and no --wheels folder was "
                         "given: fetch them with benchmarks/fetch_gpu_wheels.py where there is network (docs/gpu.md)")
    cmd = [sys.executable, "-m", "pip", "install", "--quiet", "--no-index", "--no-deps", "--no-warn-script-location",
           "--find-links", str(wheels), "--target", str(site), *missing]
    print(f"[setup] {shlex.join(cmd)}", flush=True)
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"gpu_validate: installing {', '.join(missing)} from {wheels} failed:\n{r.stderr[-3000:]}")
    use_site(site)
    still = missing_modules()
    if still:
        raise SystemExit(f"gpu_validate: {', '.join(still)} still cannot be imported after installing into {site}")
    return missing


def unpack_deb(deb: Path, dest: Path) -> None:
    """Extract a Debian package's files (its data.tar.*) under `dest`, as `dpkg -x` would, without dpkg."""
    blob = deb.read_bytes()
    if not blob.startswith(b"!<arch>\n"):
        raise SystemExit(f"gpu_validate: {deb} is not a Debian package (no ar header)")
    pos = 8
    while pos + 60 <= len(blob):
        name, size = blob[pos:pos + 16].decode().strip().rstrip("/"), int(blob[pos + 48:pos + 58].decode())
        body = blob[pos + 60:pos + 60 + size]
        if name.startswith("data.tar"):
            with tarfile.open(fileobj=io.BytesIO(body)) as tar:
                tar.extractall(dest, filter="data")
            return
        pos += 60 + size + (size & 1)
    raise SystemExit(f"gpu_validate: {deb} holds no data.tar member")


def can_load(library: str, env: dict[str, str]) -> bool:
    """Whether a process started with `env` can dlopen `library` (LD_LIBRARY_PATH is read at start)."""
    probe = f"import ctypes; ctypes.CDLL({library!r})"
    return subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True).returncode == 0


def egl_environment(env: dict[str, str], work: Path, wheels: Path | None) -> list[str]:
    """Make headless EGL reachable from processes started with `env`; returns what was done.

    PyOpenGL opens glvnd's libEGL.so.1, which hands the context to a vendor library named by a
    JSON file. The GPU image has the NVIDIA driver's vendor library and its JSON under
    /usr/local/nvidia, outside glvnd's search path, and may lack glvnd itself; its loaders travel
    as Debian packages in WHEELS/debs (fetch_gpu_wheels.py).
    """
    notes = []
    env.setdefault("PYOPENGL_PLATFORM", "egl")
    libdirs = [d for d in ("/usr/local/nvidia/lib64", "/usr/local/nvidia/lib") if Path(d).is_dir()]
    if not can_load("libEGL.so.1", env):
        debs = sorted((wheels / "debs").glob("*.deb")) if wheels else []
        if not debs:
            raise SystemExit("gpu_validate: libEGL.so.1 cannot be loaded here and --wheels has no debs/ folder: "
                             "fetch_gpu_wheels.py downloads glvnd's loaders (docs/gpu.md)")
        gl = work / "gl"
        for deb in debs:
            unpack_deb(deb, gl)
        libdirs.insert(0, str(gl / DEB_LIBDIR))
        notes.append(f"glvnd's loaders unpacked from {len(debs)} packages into {gl}")
    if libdirs:
        env["LD_LIBRARY_PATH"] = os.pathsep.join([*libdirs, *filter(None, [env.get("LD_LIBRARY_PATH")])])
    vendors = [str(p) for d in GLVND_VENDOR_DIRS if d.is_dir() for p in sorted(d.glob("*.json"))]
    if NVIDIA_EGL_VENDOR.exists() and str(NVIDIA_EGL_VENDOR) not in vendors and "__EGL_VENDOR_LIBRARY_FILENAMES" not in env:
        env["__EGL_VENDOR_LIBRARY_FILENAMES"] = os.pathsep.join([str(NVIDIA_EGL_VENDOR), *vendors])
        notes.append(f"EGL vendors: {env['__EGL_VENDOR_LIBRARY_FILENAMES']}")
    return notes


def gl_renderer(env: dict[str, str]) -> str:
    """The GL renderer the raster backend's context gets (a GPU's name, or llvmpipe: software)."""
    probe = ("from omnigen.scenes.gl_raster import GLRaster; from OpenGL import GL; GLRaster(); "
             "print(GL.glGetString(GL.GL_RENDERER).decode())")
    r = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, cwd=ROOT)
    if r.returncode:
        raise SystemExit("gpu_validate: the raster backend could not make a headless EGL context "
                         f"(docs/gpu.md, 'EGL'):\n{r.stderr[-3000:]}")
    return r.stdout.strip().splitlines()[-1]


THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


PARTS = ("scenes", "rigs", "converters", "detector")


def checkout_namespace(dest: Path) -> Path:
    """A folder that holds `omnigen` as an installation lays it out, made of links into this checkout.

    An installation maps the part folders into the omnigen namespace (pyproject's package-dir); a
    machine that cannot install runs the checkout as it is, so `omnigen/`'s entries and the part
    folders are linked side by side under dest/omnigen. Idempotent; returns dest, to go first on
    the path."""
    pkg = dest / "omnigen"
    pkg.mkdir(parents=True, exist_ok=True)
    sources = [p for p in (ROOT / "omnigen").iterdir() if p.name != "__pycache__"]
    for src in sources + [ROOT / part for part in PARTS]:
        link = pkg / src.name
        if not link.is_symlink():
            link.symlink_to(src)
    return dest


def child_environment(site: Path) -> dict[str, str]:
    """The environment of the processes this run starts: our code (as checkout_namespace lays it out
    beside WORK/site) and WORK/site importable, and one thread each for the numerical libraries
    (--jobs renders share the cores)."""
    env = dict(os.environ)
    ours = checkout_namespace(site.parent / "namespace")
    env["PYTHONPATH"] = os.pathsep.join([str(ours), str(ROOT), str(site), *filter(None, [env.get("PYTHONPATH")])])
    env.update({k: "1" for k in THREAD_VARIABLES})
    return env


# ---------------------------------------------------------------------------------------------
# stages
# ---------------------------------------------------------------------------------------------


class Stages:
    """Each stage's wall time, kept in WORK/stages.json: a stage skipped on resume keeps the time
    it took when it ran, so results.json reports the whole run's stages."""

    def __init__(self, work: Path) -> None:
        from omnigen.files import atomic_write_json

        self._write = atomic_write_json
        self.path = work / "stages.json"
        self.seconds: dict[str, float] = json.loads(self.path.read_text()) if self.path.exists() else {}

    def done(self, name: str, seconds: float, ran: bool, budget: float) -> None:
        if ran:
            self.seconds[name] = round(seconds, 1)
            self._write(self.path, self.seconds, indent=1)
        took = self.seconds.get(name, 0.0)
        note = "" if ran else " (done earlier)"
        print(f"gpu_validate: stage {name} {took:.1f} s{note} (budget {budget:.0f} s)", flush=True)


def default_kitti() -> Path | None:
    """The KITTI sample beside the checkout (../shared), else inside it (shared/, what the device tool carries)."""
    for p in (ROOT.parent / "shared" / "realdata" / "kitti", ROOT / "shared" / "realdata" / "kitti"):
        if (p / "training").is_dir():
            return p
    return None


def render_stage(run, work: Path, args: argparse.Namespace, env: dict[str, str]) -> tuple[list[Path], list[Path], bool]:
    """The `make validate` cities and the extra training cities, rendered --jobs at a time, longest
    jobs first; returns (validate's renders, the extra ones, whether anything was rendered)."""
    base_frames = args.cities * args.city_frames
    data = {"size": args.size, "backend": "raster", "seed": args.seed, "scene": args.scene}
    base = render_jobs(work, argparse.Namespace(frames=base_frames, cities=args.cities, **data))
    extra_frames = max(0, args.frames - base_frames)
    extra_cities = min(extra_frames, max(1, math.ceil(args.jobs / 3))) if extra_frames else 0
    extra = render_jobs(work, argparse.Namespace(frames=extra_frames, cities=extra_cities, **data),
                        first_city=args.cities) if extra_frames else []
    todo = [argv for argv, out in extra + base if not (out / "manifest.json").exists()]
    run_renders(run, todo, args.jobs, env)
    return [out for _, out in base], [out for _, out in extra], bool(todo)


def data_stage(run, work: Path, base: list[Path], extra: list[Path], args: argparse.Namespace) -> tuple[Path, bool]:
    """KITTI converted; `make validate`'s merge (its test split); the whole merge with that split pinned."""
    ran = 0.0
    real = []
    if args.kitti:
        ran += run(["convert", "kitti", str(args.kitti), "--out", str(work / "kitti")], work / "kitti" / "manifest.json")
        real.append(work / "kitti")
    split_from, uov = work / "uov-validate", work / "uov"
    ran += run(["merge", *map(str, base + real), "--out", str(split_from), "--test-fraction", str(args.test_fraction),
                "--seed", str(args.seed)], split_from / "manifest.json")
    ran += run(["merge", *map(str, base + extra + real), "--out", str(uov), "--test-fraction", "0",
                "--split-file", str(split_from / "splits" / "test.txt"), "--seed", str(args.seed)], uov / "manifest.json")
    return uov, ran > 0


def train_arguments(uov: Path, out: Path, args: argparse.Namespace) -> list[str]:
    """`omnigen train`: the recipe (detector/recipe.py: make validate's, windows and crop stage
    included; --train-args' KEY=VALUE changes it) on the data, its schedule fitted to --minutes
    (--time, both phases), the images cached; nothing of the recipe's own values."""
    budget = ["--time", f"{args.minutes:g}", "--epochs", str(MAX_EPOCHS)]
    return ["train", str(uov), *shlex.split(getattr(args, "train_args", "") or ""), "--out", str(out),
            "--workers", str(args.workers), "--seed", str(args.seed), "--val-every", str(args.val_every),
            "--amp", "auto", "--cache", "--device", args.device, *budget]


def trained_recipe(args: argparse.Namespace) -> Any:
    """The recipe train_arguments trains (for the report's input size and batch, and the peer's)."""
    from omnigen.detector.recipe import RECIPE, with_overrides

    return with_overrides(RECIPE, shlex.split(getattr(args, "train_args", "") or ""))


def training_speed(run_dir: Path, train_frames: int) -> dict[str, Any]:
    """From results.csv: epochs, the steps' seconds (each epoch's `seconds`: loader and steps, no
    validation), the whole training's (`time`), and training images a second over the steps."""
    rows = list(csv.DictReader((run_dir / "results.csv").read_text().splitlines()))
    steps = sum(float(r["seconds"]) for r in rows)
    images = train_frames * len(rows)
    return {"epochs": len(rows), "train_frames": train_frames, "images": images, "step_seconds": round(steps, 1),
            "seconds": round(float(rows[-1]["time"]), 1) if rows else 0.0,
            "images_per_s": round(images / steps, 1) if steps > 0 else None}


def device_name(device: str) -> str:
    import torch

    if device.startswith("cuda") and torch.cuda.is_available():
        return torch.cuda.get_device_name(torch.device(device))
    return f"CPU ({platform.processor() or platform.machine()}, {usable_cores()} cores)"


def git_commit() -> str | None:
    """The checkout's commit, when it is a git work tree and git is there (a copied tree may be neither)."""
    try:
        r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    except OSError:
        return None
    return (r.stdout.strip() or None) if r.returncode == 0 else None


def cpu_reference(results_dir: Path) -> dict[str, Any] | None:
    """make validate's main row from results.json beside RESULTS.md, for the table's CPU column."""
    path = results_dir / "results.json"
    if not path.exists():
        return None
    r = json.loads(path.read_text())
    main = next((run for run in r.get("runs", []) if run.get("name") == "n-p2"), None)
    if main is None:
        return None
    return {"machine": r.get("machine"), "date": r.get("date"), "train_seconds": main.get("train_seconds"),
            "epochs": main.get("epochs_logged"), "imgsz": main.get("imgsz"), "crop": main.get("crop"),
            "test_frames": ((r.get("frames") or {}).get("splits") or {}).get("test", {}).get("frames"),
            "synthetic": metric_row(main["synthetic_test"])}


def section_markdown(r: dict[str, Any]) -> str:
    """The RESULTS.md section: every number read from results.json, which this script wrote."""
    a, t, s = r["arguments"], r["training"], r["synthetic"]
    unused = ("work", "wheels", "results", "kitti")
    cmd = "python benchmarks/gpu_validate.py " + " ".join(
        f"--{k.replace('_', '-')}" + ("" if v is True else f" {v}") for k, v in a.items()
        if v not in (None, False) and k not in unused)
    made = f"Made by `{cmd}` on {r['machine']}, {r['date']}" + (f", commit {r['commit']}." if r.get("commit") else ".")
    cpu = r.get("cpu_reference")
    lines = ["## On one GPU, time-boxed (benchmarks/gpu_validate.py)", "",
             "Rendered, trained and evaluated on one machine within a wall-clock budget (docs/gpu.md). The test",
             "split is `make validate`'s: its cities rendered with the same seeds and merged with the same",
             "KITTI frames, so the figures stand beside the CPU run's (the GPU's rasteriser draws the same",
             "scenes; pixels may differ slightly). The other cities were rendered for training only.",
             "",
             f"- device: {r['device']}; GL renderer of the raster backend: {r['gl_renderer']}",
             f"- frames: {r['frames']['total']} ({', '.join(f'{k} {v}' for k, v in r['frames']['by_source'].items())}); "
             f"train {r['frames']['train']}, test {r['frames']['test']}",
             f"- training: {t['epochs']} epochs of {t['train_frames']} frames at {t['imgsz']} px, batch {t['batch']}, "
             f"{t['step_seconds']} s of steps ({t['seconds']} s with validation): "
             f"{fmt(t['images_per_s'], 1)} training images/s",
             "",
             "| stage | seconds | budget (s) |", "|---|---|---|",
             *[f"| {k} | {v} | {fmt(r['stage_budgets'].get(k), 0)} |" for k, v in r["stage_seconds"].items()],
             f"| total | {r['total_seconds']} | {BUDGET_SECONDS} |",
             "",
             "| synthetic test split | this run |" + (" make validate (CPU) |" if cpu else ""),
             "|---|---|" + ("---|" if cpu else "")]
    rows = [("OKS mAP50:95", "oks_map50_95", 3), ("AP at OKS 0.50", "ap_oks50", 3), ("F1 at OKS 0.5", "f1", 3),
            ("ground-plane adherence (deg)", "ground_adherence_deg", 2),
            ("median corner error of box-matched objects (px)", "corner_error_px", 2),
            ("the same, relative to sqrt(box area)", "corner_error_rel", 3)]
    base = r.get("baseline") or {}
    for label, key, digits in rows:
        lines.append(f"| {label} | {fmt(s.get(key), digits)} |" + (f" {fmt(cpu['synthetic'].get(key), digits)} |" if cpu else ""))
        if key.startswith("corner_error") and base:
            lines.append(f"| {label}, box-template baseline | {fmt(base.get(key), digits)} |" + (" |" if cpu else ""))
    lines.append(f"| test frames (synthetic) | {s.get('images')} |" + (f" {cpu['synthetic'].get('images')} |" if cpu else ""))
    if cpu:
        crop = f" (crop {cpu['crop']})" if cpu.get("crop") else ""
        lines.append(f"| training | {t['seconds']} s, {t['epochs']} epochs, {t['imgsz']} px |"
                     f" {cpu['train_seconds']} s, {cpu['epochs']} epochs, {cpu['imgsz']} px{crop}; {cpu['machine']} |")
    peer = r.get("peer")
    if peer:
        lines += ["", f"Beside it, on the same data for the same minutes: {peer['model']} "
                      f"(Ultralytics {peer['ultralytics']}, from scratch; benchmarks/peer_ultralytics.py): synthetic "
                      f"mAP50:95 {fmt(peer['synthetic'].get('oks_map50_95'))}, AP50 {fmt(peer['synthetic'].get('ap_oks50'))}, "
                      f"adherence {fmt(peer['synthetic'].get('ground_adherence_deg'), 2)} deg, {peer['epochs']} epochs."]
    lines += ["", made]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------------


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    cores = usable_cores()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="working folder (resumable)")
    ap.add_argument("--device", default=None, help="cuda or cpu (default: cuda when there is one)")
    ap.add_argument("--frames", type=int, default=800, help="frames per rig, the --cities x --city-frames of make validate's included")
    ap.add_argument("--cities", type=int, default=5, help="make validate's cities per rig (its test split's groups)")
    ap.add_argument("--city-frames", type=int, default=40, help="frames of each of those cities")
    ap.add_argument("--test-fraction", type=float, default=0.2, help="of make validate's merge (its test split)")
    ap.add_argument("--size", type=int, default=640, help="rendered width and height")
    ap.add_argument("--scene", default=SCENE_MIX, help="city preset or mix (default: make validate's mix)")
    ap.add_argument("--minutes", type=float, default=7.0, help="training's wall-clock budget (train --time)")
    ap.add_argument("--batch", type=int, default=64, help="images a batch of the evaluation")
    ap.add_argument("--val-every", type=int, default=10, help="validate every N epochs (train stretches it under --time)")
    ap.add_argument("--jobs", type=int, default=cores, help="concurrent render processes")
    ap.add_argument("--workers", type=int, default=max(0, cores - 2), help="training's data loader processes")
    ap.add_argument("--wheels", type=Path, default=None, help="folder from fetch_gpu_wheels.py (wheels, debs/)")
    ap.add_argument("--kitti", type=Path, default=default_kitti(), help="KITTI tree to merge (default: the shared sample)")
    ap.add_argument("--no-kitti", action="store_true", help="synthetic frames alone")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--train-args", default="",
                    help="recipe keys to change, one string of KEY=VALUE (omnigen train's; e.g. a recipe from "
                         "bench_learning.py tried on the GPU); default: none, make validate's recipe as it is")
    ap.add_argument("--results", type=Path, default=ROOT / "docs", help="folder of RESULTS.md (its section) and gpu_results.json")
    ap.add_argument("--peer", action="store_true", help="also train Ultralytics' YOLO11n-pose (peer_ultralytics.py)")
    args = ap.parse_args(argv)
    if args.no_kitti:
        args.kitti = None
    if args.frames < args.cities * args.city_frames:
        ap.error(f"--frames {args.frames} is fewer than --cities x --city-frames ({args.cities * args.city_frames})")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    started = time.perf_counter()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    site = work / "site"
    sys.path.insert(0, str(checkout_namespace(work / "namespace")))

    t = time.perf_counter()
    installed = install_missing(args.wheels, site)
    env = child_environment(site)
    notes = egl_environment(env, work, args.wheels)
    renderer = gl_renderer(env)
    print(f"[setup] GL renderer: {renderer}" + "".join(f"; {n}" for n in notes), flush=True)

    import torch

    from omnigen.files import atomic_write_json, atomic_write_text
    from omnigen.splits import read_split

    args.device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    stages = Stages(work)
    stages.done("setup", time.perf_counter() - t, True, STAGE_BUDGETS["setup"])
    check_data_arguments(work, args, ("frames", "cities", "city_frames", "test_fraction", "size", "scene", "seed", "kitti"))
    run = Runner(work, who="gpu_validate")

    t = time.perf_counter()
    base, extra, ran = render_stage(run, work, args, env)
    stages.done("render", time.perf_counter() - t, ran, STAGE_BUDGETS["render"])

    t = time.perf_counter()
    uov, ran = data_stage(run, work, base, extra, args)
    stages.done("data", time.perf_counter() - t, ran, STAGE_BUDGETS["data"])

    t = time.perf_counter()
    out = work / "runs" / "n-p2"
    train_frames = len(read_split(uov, "train"))
    ran = not (out / "done").exists()
    train_stage(run, train_arguments(uov, out, args), out)
    stages.done("train", time.perf_counter() - t, ran, args.minutes * 60 + 30)

    t = time.perf_counter()
    report_path = out / "eval.json"
    ran = run(["eval", str(out / "last.pt"), str(uov), "--split", "test", "--batch", str(args.batch),
               "--device", args.device, "--baseline", "--out", str(report_path)], report_path) > 0
    stages.done("eval", time.perf_counter() - t, ran, STAGE_BUDGETS["eval"])
    report = json.loads(report_path.read_text())

    recipe = trained_recipe(args)
    peer = None
    if args.peer:
        cmd = [sys.executable, str(ROOT / "benchmarks" / "peer_ultralytics.py"), "--work", str(work), "--minutes",
               f"{args.minutes:g}", "--imgsz", str(recipe.model.imgsz), "--batch", str(recipe.optim.batch), "--workers",
               str(args.workers), "--device", args.device]
        print(f"[peer] {shlex.join(cmd)}", flush=True)
        # one process trains there, as here: the thread caps of the renders are lifted
        peer_env = {k: v for k, v in env.items() if k not in THREAD_VARIABLES}
        peer_env.update({k: os.environ[k] for k in THREAD_VARIABLES if k in os.environ})
        subprocess.run(cmd, env=peer_env)
        peer_path = work / "peer" / "result.json"
        peer = json.loads(peer_path.read_text()) if peer_path.exists() else None

    manifest = json.loads((uov / "manifest.json").read_text())
    splits = manifest.get("splits") or {}
    results = {
        "device": device_name(args.device), "machine": machine(), "gl_renderer": renderer,
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "commit": git_commit(),
        "installed": installed,
        "frames": {"total": manifest["counts"]["frames"], "by_source": manifest["counts"]["frames_by_source"],
                   "rendered_per_rig": args.frames, "train": splits.get("train", {}).get("frames"),
                   "test": splits.get("test", {}).get("frames")},
        "stage_seconds": dict(stages.seconds), "stage_budgets": {**STAGE_BUDGETS, "train": args.minutes * 60 + 30},
        "total_seconds": round(sum(stages.seconds.values()), 1), "budget_seconds": BUDGET_SECONDS,
        "training": {**training_speed(out, train_frames), "imgsz": recipe.model.imgsz, "batch": recipe.optim.batch,
                     "window": recipe.data.window if 0 < recipe.data.window < recipe.model.imgsz else None},
        "synthetic": metric_row(synthetic_row(report)), "overall": metric_row(report["report"]["rows"][0]),
        "baseline": metric_row(synthetic_row({"report": report["baseline"]})) if "baseline" in report else None,
        "arguments": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        "cpu_reference": cpu_reference(args.results), "peer": peer,
    }
    results["within_budget"] = results["total_seconds"] <= BUDGET_SECONDS
    atomic_write_json(work / "results.json", results, indent=2)
    args.results.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.results / "gpu_results.json", results, indent=2)
    md = args.results / "RESULTS.md"
    atomic_write_text(md, with_section(md.read_text() if md.exists() else "", SECTION, section_markdown(results)))
    print(f"gpu_validate: wrote {work / 'results.json'} and the '{SECTION}' section of {md}; "
          f"{results['total_seconds']:.0f} s of stages ({time.perf_counter() - started:.0f} s this invocation), "
          f"budget {BUDGET_SECONDS} s")
    s, speed = results["synthetic"], results["training"]["images_per_s"]
    print(f"gpu_validate: synthetic mAP50:95 {fmt(s['oks_map50_95'])}, adherence {fmt(s['ground_adherence_deg'], 2)} deg, "
          f"{fmt(speed, 1)} img/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
