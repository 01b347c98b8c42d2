"""What the benchmark scripts share: the one module a script imports another script's code from.

Importing it needs the standard library alone: gpu_validate.py and peer_ultralytics.py import it
before their setup stage has made numpy, PIL and omnigen importable on a bare GPU machine, so every
other import is made inside the function that needs it.

- fake_dataset: large fake datasets, generated once and cached between runs (bench_load,
  bench_stats, bench_merge_export, bench_eval).
- fmt, stale, Runner: a figure in a table, a done-marker written with other arguments, omnigen
  commands run in this process with their wall times kept (validate, gpu_validate, bench_learning,
  peer_ultralytics).
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


class Runner:
    """Runs omnigen commands in this process, records each with its wall time (in WORK/commands.json,
    so that a resumed run reports the stages an earlier invocation did), and stops on failure.

    `key` says which records are one piece of work: a subclass may leave out of it the flags that
    change how fast a command runs, not what it makes (validate.py: train's --cache)."""

    def __init__(self, work: Path, who: str = "benchmarks") -> None:
        self.path = work / "commands.json"
        self.who = who  # the script named in the failure line
        self.log: list[dict[str, Any]] = json.loads(self.path.read_text()) if self.path.exists() else []

    def key(self, command: str) -> str:
        return command

    @staticmethod
    def omnigen(argv: list[str]) -> int:
        """`omnigen ARGV` in this process (tests replace it)."""
        from omnigen.cli import main

        return main(argv)

    def save(self) -> None:
        from omnigen.files import atomic_write_json

        atomic_write_json(self.path, self.log, indent=1)

    def record(self, command: str, seconds: float) -> None:
        """Log a finished command; one run again (its output deleted to redo it) replaces its record."""
        self.log = [c for c in self.log if c["command"] != command]
        self.log.append({"command": command, "seconds": round(seconds, 1)})
        self.save()

    def seconds(self, prefix: str) -> float:
        """Wall time of the recorded commands that start with `prefix` (compared by `key`)."""
        prefix = self.key(prefix)
        return sum(c["seconds"] for c in self.log if self.key(c["command"]).startswith(prefix))

    def drop(self, prefix: str) -> None:
        """Drop the records of commands that start with `prefix` (redone in another form)."""
        self.log = [c for c in self.log if not c["command"].startswith(prefix)]
        self.save()

    def forget(self, folder: Path) -> None:
        """Drop the records of commands that wrote into or read from `folder` (it is being redone)."""
        self.log = [c for c in self.log if not mentions(c["command"], folder)]
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
        t = time.perf_counter()
        rc = self.omnigen(invoked)
        dt = time.perf_counter() - t
        if rc != 0:
            raise SystemExit(f"{self.who}: 'omnigen {shlex.join(invoked)}' exited with {rc}")
        self.record(cmd, (resume_from or 0.0) + dt)
        return dt


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
