"""What the benchmark scripts share: the one module a script imports another script's code from.

Importing it needs the standard library alone: gpu_validate.py and peer_ultralytics.py import it
before their setup stage has made numpy, PIL and omnigen importable on a bare GPU machine, so every
other import is made inside the function that needs it.

- fake_dataset: large fake datasets, generated once and cached between runs (bench_load,
  bench_stats, bench_merge_export, bench_eval).
- fmt, stale, Runner: a figure in a table, a done-marker written with other arguments, omnigen
  commands run in this process with their wall times kept (validate, gpu_validate, bench_learning,
  peer_ultralytics).
- the stages validate and gpu_validate both run: the renders (render_jobs, run_renders, SCENE_MIX),
  a training resumed or redone by its done-marker (train_stage), the data arguments a working
  folder was made with (check_data_arguments), the machine's line, and RESULTS.md's sections that
  each script owns (with_section, kept_sections).
- synthetic_row, metric_row: the rows of an `omnigen eval` report the GPU results are made of.
- usable_cores, use_site: the cores this process may use; the folder gpu_validate installs into.
- NEEDS: the distributions gpu_validate installs on the GPU machine and fetch_gpu_wheels.py fetches.
- floor_rows: what the evaluation gives the ground truth's own corners (bench_adherence_floor, validate).
"""

from __future__ import annotations

import importlib
import json
import math
import os
import re
import shlex
import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

    from omnigen.dataset import Dataset
    from omnigen.taxonomy import Taxonomy

# ---------------------------------------------------------------------------------------------
# fake datasets
# ---------------------------------------------------------------------------------------------

CACHE = Path(tempfile.gettempdir()) / "omnigen-bench"
VIEWS = {"synthetic": ("ego", "infrastructure", "aerial"), "kitti": ("ego",), "dair-v2x-i": ("infrastructure",)}


def _write_range(args: tuple[str, str, int, int, int, bool]) -> None:
    """Frames start..stop of a fake dataset, written by one of fake_dataset's processes."""
    from PIL import Image

    from omnigen.fakes import random_frame
    from omnigen.writer import DatasetWriter

    root, source, start, stop, seed, images = args
    writer = DatasetWriter(root, durable=False)
    views = VIEWS[source]
    for i in range(start, stop):
        rec = random_frame(seed, i, source, views[i % len(views)], n_objects=8 if i % 2 else 7,
                           width=64, height=40)
        if images:
            Image.new("RGB", (rec.width, rec.height), (i % 251, (i // 251) % 251, seed % 251)).save(Path(root) / rec.image)
            if rec.synthetic is not None:
                for rel in (rec.synthetic.depth, rec.synthetic.instance):
                    (Path(root) / rel).write_bytes(f"{rel}".encode())
        writer.write(rec)


def fake_dataset(name: str, frames: int, source: str = "synthetic", seed: int = 0, images: bool = True) -> Path:
    """A finalized fake dataset under the benchmark cache, generated on first use (by two processes):
    omnigen.fakes' frames (real geometry, random scenes), 7 and 8 objects a frame in turn, so that
    40,000 frames hold 300,000 objects. Large sizes take minutes, hence the cache."""
    from omnigen.writer import DatasetWriter

    root = CACHE / name
    if (root / "manifest.json").exists():
        return root
    shutil.rmtree(root, ignore_errors=True)
    for sub in ("images", "depth", "instance"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    jobs = [(str(root), source, s, min(s + 1000, frames), seed, images) for s in range(0, frames, 1000)]
    with ProcessPoolExecutor(2) as pool:
        list(pool.map(_write_range, jobs))
    DatasetWriter(root).finalize({"name": name}, show_progress=True)
    print(f"generated {name}: {frames} frames in {time.perf_counter() - t:.1f} s at {root}")
    return root


# ---------------------------------------------------------------------------------------------
# tables, done-markers and omnigen commands
# ---------------------------------------------------------------------------------------------


def fmt(v: Any, digits: int = 3) -> str:
    """A figure for a table: '-' where there is none (None, or NaN: nothing was matched)."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def stale(marker: Path, stamp: str) -> bool:
    """A done-marker left by a run with other arguments (or other inputs): its work is redone."""
    return marker.exists() and marker.read_text().strip() != stamp


def mentions(command: str, folder: Path) -> bool:
    """Whether a recorded command names `folder` or a file in it (not a sibling sharing its prefix)."""
    return re.search(re.escape(str(folder)) + r"(?=[/ ,)]|$)", command) is not None


# train flags that change how fast a run learns, not what it learns (tests/detector/test_detector_train.py
# checks that the image cache trains the same weights): a run done without them is not redone with them
SAME_WEIGHTS = ("--cache",)


def train_stamp(command: str) -> str:
    """A training command without the flags that leave its weights alone: what its done-marker holds."""
    return " ".join(t for t in command.split(" ") if t not in SAME_WEIGHTS)


def trains_into(command: str, out: Path) -> bool:
    """Whether a recorded command is an `omnigen train` whose --out is `out` (not one that only
    reads from it, e.g. --weights OUT/last.pt)."""
    argv = shlex.split(command)
    return argv[:2] == ["omnigen", "train"] and "--out" in argv[:-1] and Path(argv[argv.index("--out") + 1]) == out


class Runner:
    """Runs omnigen commands in this process, records each with its wall time (in WORK/commands.json,
    so that a resumed run reports the stages an earlier invocation did), and stops on failure.
    Records are compared by their train_stamp: a training with --cache or without is one piece of
    work."""

    def __init__(self, work: Path, who: str = "benchmarks") -> None:
        self.path = work / "commands.json"
        self.who = who  # the script named in the failure lines
        self.log: list[dict[str, Any]] = json.loads(self.path.read_text()) if self.path.exists() else []

    @staticmethod
    def omnigen(argv: list[str]) -> int:
        """`omnigen ARGV` in this process (tests replace it)."""
        from omnigen.cli import main

        return main(argv)

    def save(self) -> None:
        from omnigen.files import atomic_write_json

        atomic_write_json(self.path, self.log, indent=1)

    def record(self, command: str, seconds: float, cpu_share: float | None = None, now: bool = True) -> None:
        """Log a finished command; one run again (its output deleted to redo it) replaces its record.

        Beside its wall time: the 1-minute load average as it ended and, for a command run in this
        process, the share of the usable cores' time it used (`cpu_share`). Why: on a 2-core machine
        a training's two OpenMP threads slow 10-fold when a third job shares the cores, and the
        wall times alone do not say whether a run had the machine to itself (a quiet training reads
        a share near 1 and a load near 2). The share counts this process's threads, not a loader's
        worker processes, and for a resumed training the last invocation only. `now=False`: a command
        that did not just end (a training recovered from its results.csv) gets no load, which would be
        this moment's."""
        self.log = [c for c in self.log if c["command"] != command]
        entry: dict[str, Any] = {"command": command, "seconds": round(seconds, 1)}
        if now:
            entry["load"] = round(os.getloadavg()[0], 2)
        if cpu_share is not None:
            entry["cpu_share"] = round(cpu_share, 2)
        self.log.append(entry)
        self.save()

    def seconds(self, prefix: str) -> float:
        """Wall time of the recorded commands that start with `prefix`, --cache or not (train_stamp)."""
        prefix = train_stamp(prefix)
        return sum(c["seconds"] for c in self.log if train_stamp(c["command"]).startswith(prefix))

    def drop(self, prefix: str) -> None:
        """Drop the records of commands that start with `prefix` (redone in another form)."""
        self.log = [c for c in self.log if not c["command"].startswith(prefix)]
        self.save()

    def forget(self, folder: Path) -> None:
        """Drop the records of commands that wrote into or read from `folder` (it is being redone)."""
        self.log = [c for c in self.log if not mentions(c["command"], folder)]
        self.save()

    def forget_trainings(self, out: Path, but: str | None = None) -> None:
        """Drop the records of trainings into `out` (trains_into), but those of the training `but`
        (--cache or not, train_stamp): a folder trained again, or moved back from another run."""
        keep = None if but is None else train_stamp(but)
        self.log = [c for c in self.log if not trains_into(c["command"], out) or train_stamp(c["command"]) == keep]
        self.save()

    def __call__(self, argv: list[str], done: Path | None = None, resume_from: float | None = None) -> float:
        """Run `omnigen ARGV` unless `done` exists; `resume_from` (a training's seconds before it was
        cut off) runs it with --resume and records it under ARGV with those seconds added."""
        cmd = "omnigen " + shlex.join(argv)
        if done is not None and done.exists():
            print(f"[skip, done] {cmd}", flush=True)
            return 0.0
        invoked = argv if resume_from is None else [*argv, "--resume"]
        print(f"[run] omnigen {shlex.join(invoked)}", flush=True)
        t, cpu = time.perf_counter(), time.process_time()
        rc = self.omnigen(invoked)
        dt, used = time.perf_counter() - t, time.process_time() - cpu
        if rc != 0:
            raise SystemExit(f"{self.who}: 'omnigen {shlex.join(invoked)}' exited with {rc}")
        self.record(cmd, (resume_from or 0.0) + dt, used / (dt * usable_cores()) if dt > 0 else None)
        return dt


# ---------------------------------------------------------------------------------------------
# the stages validate.py and gpu_validate.py share
# ---------------------------------------------------------------------------------------------

RIGS = ("ego", "pole", "drone")
SCENE_MIX = "downtown,suburban,arterial,intersection"
"""The presets make validate's cities are drawn from: city seed s gets the (s mod 4)-th (omnigen
render --scene with a mix), so each rig's consecutive seeds cover all four."""


def trained_seconds(out: Path) -> float:
    """The seconds a run's saved epochs took, over all its invocations (results.csv's `time`)."""
    import csv

    path = out / "results.csv"
    rows = list(csv.DictReader(path.read_text().splitlines())) if path.exists() else []
    return float(rows[-1].get("time") or 0.0) if rows else 0.0


def train_stage(run: Runner, train_cmd: list[str], out: Path) -> float:
    """Train into `out` unless its done-marker says it was trained with these arguments; returns
    the training's seconds, over all the invocations it took.

    A run cut off midway (its `started` marker holds these arguments and it has a last.pt) goes on
    from that checkpoint; a folder from other arguments, or cut off before its first checkpoint,
    is trained again from the start.
    """
    from omnigen.files import atomic_write_text

    stamp = train_stamp(shlex.join(train_cmd))
    done, started = out / "done", out / "started"
    if stale(done, stamp):  # e.g. more --epochs than last time: train again
        print(f"[stale] {out} was trained with other arguments: training again", flush=True)
        shutil.rmtree(out)
        run.forget(out)
    if done.exists():
        run(train_cmd, done)  # says it skips
        cmd = "omnigen " + shlex.join(train_cmd)
        # the log must name this training, not another one that once wrote into `out` (a folder
        # moved back by hand from an earlier run): other trainings into it are dropped, and a run
        # the log lost is recorded with its epochs' own seconds (none without a results.csv, rather
        # than a 0 that reads as a figure)
        run.forget_trainings(out, but=cmd)
        seconds = trained_seconds(out)
        if seconds and not run.seconds(cmd):
            run.record(cmd, seconds, now=False)
    else:
        resumable = (out / "last.pt").exists() and started.exists() and not stale(started, stamp)
        if resumable:
            print(f"[resume] {out} goes on from its last.pt", flush=True)
        else:
            if out.exists():
                shutil.rmtree(out)
                run.forget(out)
            # a training from the start: no earlier training into `out` counts towards its seconds
            # (one whose folder was moved away left its record, perhaps with --cache and so not replaced)
            run.forget_trainings(out)
            out.mkdir(parents=True)
            atomic_write_text(started, stamp + "\n")
        run(train_cmd, done, resume_from=trained_seconds(out) if resumable else None)
        atomic_write_text(done, stamp + "\n")
    return run.seconds("omnigen " + shlex.join(train_cmd))


def check_data_arguments(work: Path, args: Any, names: tuple[str, ...]) -> None:
    """Refuse to resume a working folder whose renders and merge were made with other arguments.

    Stages are skipped when their output exists, so reusing a folder rendered at another --size
    would silently train on the old data; the arguments that shape the data (`names`, attributes
    of `args`) are kept in WORK/data.json and compared.
    """
    from omnigen.files import atomic_write_json

    wanted = {k: str(getattr(args, k)) if isinstance(getattr(args, k), Path) else getattr(args, k)
              for k in names}
    path = work / "data.json"
    if path.exists():
        had = json.loads(path.read_text())
        diff = [f"--{k} {had.get(k)} (now {v})" for k, v in wanted.items() if had.get(k) != v]
        if diff:
            raise SystemExit(f"validate: {work} holds data made with {', '.join(diff)}: "
                             f"pass --fresh to start over, or another --work")
    else:
        atomic_write_json(path, wanted, indent=1)


def render_jobs(work: Path, args: Any, first_city: int = 0) -> list[tuple[list[str], Path]]:
    """The render command and output folder of each rig's --cities cities, numbered from
    `first_city` (the seed of city c of rig i is --seed + 100 i + c); a finished one is said skipped."""
    per_city = max(1, args.frames // args.cities)
    jobs = []
    for i, rig in enumerate(RIGS):
        for c in range(first_city, first_city + args.cities):
            seed = args.seed + 100 * i + c
            out = work / f"render-{rig}-s{seed}"
            argv = ["render", "--rig", rig, "--frames", str(per_city), "--seed", str(seed), "--width", str(args.size),
                    "--height", str(args.size), "--backend", args.backend, "--quality", "preview", "--out", str(out)]
            if getattr(args, "scene", None):  # validate: the preset mix; gpu_validate: its --scene (tiny in its test)
                argv += ["--scene", args.scene]
            if (out / "manifest.json").exists():
                print(f"[skip, done] omnigen {shlex.join(argv)}", flush=True)
            jobs.append((argv, out))
    return jobs


def run_renders(run: Runner, todo: list[list[str]], jobs: int, env: dict[str, str] | None = None) -> None:
    """Run `omnigen ARGV` for each of `todo`, `jobs` processes at a time (in `env`, else this
    process's environment), recording each with its wall time; the first failure stops the run."""
    import subprocess

    todo = list(todo)
    running: list[tuple[list[str], subprocess.Popen, float]] = []
    while todo or running:
        while todo and len(running) < jobs:
            argv = todo.pop(0)
            print(f"[run] omnigen {shlex.join(argv)}", flush=True)
            running.append((argv, subprocess.Popen([sys.executable, "-m", "omnigen.cli", *argv],
                                                   stdout=subprocess.DEVNULL, env=env), time.perf_counter()))
        # whichever ends first frees its slot: waiting on the oldest would idle the others' slots
        while not (ended := [r for r in running if r[1].poll() is not None]):
            time.sleep(0.05)
        for argv, proc, t in ended:
            running.remove((argv, proc, t))
            if proc.returncode:
                for _, other, _ in running:
                    other.kill()
                raise SystemExit(f"{run.who}: 'omnigen {shlex.join(argv)}' exited with {proc.returncode}")
            run.record(f"omnigen {shlex.join(argv)}", time.perf_counter() - t)


def machine() -> str:
    """The machine a results file was made on: architecture, CPUs, GPU, Python."""
    import platform

    try:
        import torch
        gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    except Exception:  # torch missing is reported by the train step itself
        gpu = "no GPU"
    return f"{platform.machine()}, {os.cpu_count()} CPUs, {gpu}, Python {platform.python_version()}"


# Sections of RESULTS.md that other scripts write (benchmarks/gpu_validate.py): each between its
# own markers, kept when validate.py rewrites the rest, replaced whole by the script that owns it.
SECTION = re.compile(r"<!-- (?P<name>[\w-]+): begin -->\n.*?<!-- (?P=name): end -->\n", re.S)


def kept_sections(text: str) -> str:
    """The marked sections of a RESULTS.md, each after a blank line, to append to a rewritten one."""
    return "".join("\n" + m.group(0) for m in SECTION.finditer(text))


def with_section(text: str, name: str, body: str) -> str:
    """`text` with section `name` replaced by `body` (markers added), or appended when it has none."""
    block = f"<!-- {name}: begin -->\n{body.rstrip()}\n<!-- {name}: end -->\n"
    for m in SECTION.finditer(text):
        if m.group("name") == name:
            return text[:m.start()] + block + text[m.end():]
    gap = "" if not text or text.endswith("\n\n") else "\n" if text.endswith("\n") else "\n\n"
    return text + gap + block


# ---------------------------------------------------------------------------------------------
# evaluation reports
# ---------------------------------------------------------------------------------------------

METRIC_KEYS = ("images", "objects", "oks_map50_95", "ap_oks50", "precision", "recall", "f1", "ground_adherence_deg",
               "corner_error_px", "corner_error_rel")


def synthetic_row(report: dict[str, Any]) -> dict[str, Any]:
    """The source=synthetic row of an `omnigen eval` report (its JSON): the row the targets are set on."""
    for row in report["report"]["rows"]:
        if row["group"] == "source=synthetic":
            return row
    raise SystemExit("the evaluation has no synthetic test frames (no source=synthetic row)")


def metric_row(row: dict[str, Any]) -> dict[str, Any]:
    """The figures of a report row that a results file keeps."""
    return {k: row.get(k) for k in METRIC_KEYS}


# ---------------------------------------------------------------------------------------------
# this process
# ---------------------------------------------------------------------------------------------


def usable_cores() -> int:
    """The cores this process may run on (a container's share, not the host's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def use_site(site: Path) -> None:
    """Put WORK/site (what gpu_validate installs) on this process's path, after the checkout and
    before the interpreter's own."""
    if site.is_dir() and str(site) not in sys.path:
        sys.path.insert(1, str(site))
        importlib.invalidate_caches()


# ---------------------------------------------------------------------------------------------
# the GPU machine's wheels (fetch_gpu_wheels.py's module docstring says why exactly these)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Need:
    dist: str  # the distribution's name on the registry
    module: str  # what gpu_validate tries to import to know whether it is there
    why: str  # which of our modules (or of the needed ones) imports it


NEEDS: tuple[Need, ...] = (
    Need("orjson", "orjson", "omnigen/files.py, omnigen/formats/coco.py, detector/eval_command.py"),
    Need("shapely", "shapely", "omnigen/geometry.py, scenes/layout.py, rigs/sampling.py"),
    Need("pycocotools", "pycocotools", "detector/evaluation/oks_eval.py"),
    Need("trimesh", "trimesh", "scenes/meshes.py, scenes/assets"),
    Need("OpenEXR", "OpenEXR", "rigs/render.py: depth images"),
    Need("PyOpenGL", "OpenGL", "scenes/gl_raster.py: every GL call"),
    Need("pyrender", "pyrender", "scenes/gl_raster.py: the headless EGL context (pyrender.platforms.egl)"),
    Need("pyglet", "pyglet", "pyrender's package import (pyrender/viewer.py)"),
    Need("freetype-py", "freetype", "pyrender's package import (pyrender/font.py)"),
)


# ---------------------------------------------------------------------------------------------
# the adherence floor: the ground truth's own corners as predictions
# ---------------------------------------------------------------------------------------------


def truth_as_predictions(ds: Dataset, split: str | None, noise_px: float, rng: np.random.Generator,
                         taxonomy: Taxonomy) -> list[dict]:
    """COCO-results predictions made of the ground truth's projected corners, plus N(0, noise_px)
    on each coordinate; score 1. Classes the taxonomy drops are left out, as to_coco does."""
    import numpy as np

    from omnigen.splits import read_split

    keep = None if split is None else set(read_split(ds.root, split))
    t = ds.objects
    class_ids = taxonomy.fine_class_ids()[t.category]
    defined = np.isfinite(t.keypoints).all(axis=(1, 2)) & ~t.behind_camera.any(axis=1) & (class_ids >= 0)
    noisy = t.keypoints + rng.normal(0.0, noise_px, t.keypoints.shape) if noise_px > 0 else t.keypoints
    preds = []
    for i, frame_id in enumerate(ds.table.frame_id):
        if keep is not None and frame_id not in keep:
            continue
        for j in range(int(ds.offsets[i]), int(ds.offsets[i + 1])):
            if not defined[j]:
                continue
            kp = np.concatenate([noisy[j], np.full((8, 1), 2.0)], axis=1)
            preds.append({"frame_id": frame_id, "category_id": int(class_ids[j]) + 1,
                          "keypoints": kp.ravel().tolist(), "score": 1.0})
    return preds


def floor_rows(ds: Dataset, split: str | None, noises: list[float], seed: int) -> list[dict]:
    """One row per (noise, group): the evaluation's OKS mAP50:95 and adherence of the truth's corners,
    on the synthetic frames (the targets' rows) and per view."""
    import numpy as np

    from omnigen.detector.evaluation.oks_eval import evaluate
    from omnigen.taxonomy import recorded_taxonomy

    taxonomy = recorded_taxonomy(ds.manifest)
    rows = []
    for noise in noises:
        # one generator per level, seeded by the level itself: its draw does not depend on the others listed
        rng = np.random.default_rng([seed, round(noise * 1000)])
        preds = truth_as_predictions(ds, split, noise, rng, taxonomy)
        report = evaluate(ds, preds, split=split, taxonomy=taxonomy, sizes=False)
        for r in report.rows:
            if r.group == "source=synthetic" or r.group.startswith("view="):
                rows.append({"noise_px": noise, "group": r.group, "oks_map50_95": r.oks_map50_95,
                             "adherence_deg": r.ground_adherence_deg, "adherence_objects": r.adherence_objects,
                             "lift_failures": report.lift_failures})
    return rows
