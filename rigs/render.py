"""The render pipeline behind `omnigen render`: city once, then per frame scene, camera, render,
annotate, write.

Per frame i of a dataset with seed s (frame id `synthetic-<rig>-s<seed>-<i:06d>`):
1. the scene: `SceneGenerator(scene, s).frame(s, i)` (agents, weather, lighting from
   default_rng([s, i]); the city of (scene, s) is built once per process; a mix of presets,
   "downtown,suburban,...", gives the city the preset its seed draws, which the record's
   `synthetic.scene`, the manifest and `.render-args.json` name); a run of AHEAD_MIN_FRAMES
   frames or more draws each next frame's scene in a second process while this one renders
   (scenes/generate.py FramesAhead: the same Scene);
2. the camera: `omnigen.rigs.sampling.sample_camera` from the rig's own stream `rig_rng(s, i)`
   (drawn with the scene in that second process where there is one: `first_camera`);
3. render (backend `raster` or `cycles`), annotate (rigs/annotate.py); if fewer than the rig's
   `min_objects` objects are annotated (buildings hid what the geometric estimate counted), the
   camera is redrawn from the same stream, up to the rig's max_tries in all;
4. write images/<id>.png (RGB), depth/<id>.exr (float32 camera z in metres, channel "Z", inf
   where nothing was hit), instance/<id>.png (16-bit, 0 background, k = instance id) and last the
   record, each atomically. A frame whose record exists is skipped, so a rerun after a kill
   renders only what is missing, and since every frame depends only on (s, i) the result equals
   an uninterrupted run.

A render folder records the arguments that decide its frames in `.render-args.json` (written
before the first frame); a run into a folder whose recorded arguments differ is refused with the
differences named, so a resumed render never mixes frames of two settings (`--fresh` deletes the
folder's frames and starts over).

Shards (`RenderJob.shard = (K, N)`, `--shard K/N`) render the indices with index % N == K - 1
into one shared folder; whichever finds every frame of the run written builds the index and the
manifest (`finalize_run`), so the dataset equals an unsharded run's. `rigs/ray_executor.py`
calls `Renderer.render_frame(index)` from Ray actors (docs/rendering-at-scale.md).
"""

from __future__ import annotations

import hashlib
import io
import json
import numbers
import os
import shutil
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from omnigen.camera import Camera
from omnigen.dataset import MANIFEST, MANIFEST_MAX_BYTES, RECORDS_DIR, RENDER_ARGS_FILE, read_manifest
from omnigen.files import atomic_write_bytes, atomic_write_json, make_temp
from omnigen.index import INDEX_FILE
from omnigen.options import SEED_MAX
from omnigen.record import FrameRecord, SyntheticInfo
from omnigen.rigs.annotate import annotate
from omnigen.rigs.render_command import DEFAULT_FPS, FPS_RANGE, MAX_SEQUENCE_LENGTH
from omnigen.rigs.rig import RESOLUTION_RANGE, Rig, load_rig
from omnigen.rigs.meeting import Ride
from omnigen.rigs.sampling import DrawnCamera, Obstacles, rig_rng, sample_camera
from omnigen.scenes.description import Scene, to_dict
from omnigen.scenes.generate import FrameOverrides, FramesAhead
from omnigen.untrusted import read_regular
from omnigen.writer import DatasetWriter

BACKENDS = ("cycles", "raster")
AHEAD_MIN_FRAMES = 16
"""A run of at least this many frames draws each next frame's scene in a second process while this
one renders (FramesAhead), where it may use two cores or more: the worker's start (an interpreter,
its imports and the city: 1-3 s of CPU, on the other core) is repaid within a few frames."""
QUALITIES = ("preview", "fast", "final")
MAX_FRAME_INDEX = SEED_MAX
"""The last frame index: frame indices, like seeds, are what numpy's seeding and an int64 hold."""


def frame_id_for(rig: str, seed: int, index: int) -> str:
    return f"synthetic-{rig}-s{seed}-{index:06d}"


def sequence_id_for(scene: str, seed: int, sequence: int) -> str:
    """A rendered sequence's id: letters, digits and '-', a record's identifier."""
    return f"synthetic-{scene}-s{seed}-q{sequence:06d}"


# ---------------------------------------------------------------------------------------------
# Images on disk
# ---------------------------------------------------------------------------------------------


def png_bytes(array: np.ndarray) -> bytes:
    """RGB (H, W, 3) uint8 or 16-bit (H, W) uint16 (PIL mode I;16) as PNG bytes."""
    from PIL import Image

    img = Image.fromarray(np.ascontiguousarray(array.astype(np.uint16 if array.ndim == 2 else np.uint8)))
    if img.mode not in ("I;16", "RGB"):
        raise ValueError(f"unexpected PNG mode {img.mode}")
    buf = io.BytesIO()
    img.save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def write_depth_exr(path: str | os.PathLike, depth: np.ndarray) -> None:
    """float32 depth as a one-channel ("Z") ZIP-compressed scanline EXR, written atomically."""
    import OpenEXR

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    fd, tmp = make_temp(path.parent, ".exr")
    os.close(fd)
    try:
        with OpenEXR.File(header, {"Z": np.ascontiguousarray(depth, dtype=np.float32)}) as f:
            f.write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def read_depth_exr(path: str | os.PathLike) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        return np.asarray(f.channels()["Z"].pixels, dtype=np.float32)


def read_instance_png(path: str | os.PathLike) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as img:
        return np.asarray(img, dtype=np.uint16)


# ---------------------------------------------------------------------------------------------
# Backends
# ---------------------------------------------------------------------------------------------


@dataclass
class Rendered:
    rgb: np.ndarray | None  # None until finish() (a deferred raster render)
    depth: np.ndarray
    instance: np.ndarray
    render_seconds: float = 0.0  # the renderer's own work: Cycles' beauty path tracing; pyrender's whole render
    finish: Callable[[], np.ndarray] | None = None  # a deferred render's image (RasterScene.render(defer=True))
    shade: Callable[[], None] | None = None  # a deferred render: start its colour pass (RasterScene.render)
    develop: Callable[[], np.ndarray] | None = None  # a Cycles render: its image from the linear radiance, made by the writer
    labelled: object | None = None  # what render's `then` made of the labels (the annotation)
    then_seconds: float = 0.0  # the time `then` took on the rendering thread (not beside the renderer)


class RasterBackend:
    """pyrender (scenes/raster_backend.py): RGB, depth and masks in one call; `quality` ignored."""

    name = "raster"

    def __init__(self, scene: Scene, quality: str = "fast") -> None:
        from omnigen.scenes.raster_backend import RasterScene

        self.rs = RasterScene(scene)

    def update(self, scene: Scene) -> None:
        if scene is not self.rs.scene:
            self.rs.update(scene)

    def render(self, cam: Camera, then: Callable | None = None, defer: bool = False) -> Rendered:
        """The frame at `cam`; `then(depth, instance, silhouettes)`, given, runs on its labels
        right after the draw (Rendered.labelled, its time Rendered.then_seconds). defer: masks and
        depth only; `shade` starts the colour pass on llvmpipe's threads and `finish` gives the image."""
        t0 = time.perf_counter()
        f = self.rs.render(cam, defer=defer)
        t1 = time.perf_counter()
        labelled = then(f.depth, f.instance, partial(self.rs.render_instances, cam)) if then else None
        return Rendered(f.rgb, f.depth, f.instance, t1 - t0, f.finish, f.shade, labelled=labelled,
                        then_seconds=time.perf_counter() - t1)

    def save_blend(self, path: Path) -> Path:
        raise ValueError("--save-blend needs --backend cycles (the raster preview has no Blender scene)")

    def close(self) -> None:
        self.rs.close()


LABEL_SOURCES = ("auto", "gl", "cycles")


class CyclesBackend:
    """Blender Cycles for RGB; depth, instance ids and silhouettes from a label renderer.

    Labels come from the raster backend's id pass over the very same geometry (compile_scene's
    objects, the same camera; `labels="gl"`) or from Cycles' own one-sample label passes
    (`labels="cycles"`). Both sample each pixel at its centre, so they agree but for ties on
    exact edges (tests/rigs/test_render_cycles.py checks the two against each other). The GL passes
    cost milliseconds where each Cycles pass costs a render session; "auto" uses GL when a
    headless context can be made, else Cycles.

    The GL labels' scene lives on a thread of its own (a GL context is current on one thread), and
    a frame's label passes and what `render`'s `then` makes of them (the annotation) run there
    while Cycles path-traces: Cycles lets go of Python's lock while it renders, so they cost the
    frame only the CPU they take from the path tracer. The image itself is left to be developed
    from the linear radiance (Rendered.develop) by whoever writes it.
    """

    name = "cycles"

    def __init__(self, scene: Scene, quality: str = "fast", labels: str = "auto", device: str = "auto") -> None:
        from omnigen.scenes.blender_backend import BlenderScene

        if labels not in LABEL_SOURCES:
            raise ValueError(f"unknown label source {labels!r}; choose from {', '.join(LABEL_SOURCES)}")
        self.bs = BlenderScene(scene, device=device)
        self.bs.set_quality(quality)
        self.rs = None
        self._gl: ThreadPoolExecutor | None = None
        if labels != "cycles":
            gl = ThreadPoolExecutor(max_workers=1, thread_name_prefix="omnigen-gl")
            try:
                from omnigen.scenes.raster_backend import RasterScene

                self.rs = gl.submit(RasterScene, scene).result()
                self._gl = gl
            except Exception as exc:  # no headless GL here (EGL, PyOpenGL): Cycles draws the labels
                gl.shutdown()
                if labels == "gl":
                    raise RuntimeError(f"--labels gl: no headless OpenGL context ({exc})") from exc
        self.labels = "cycles" if self.rs is None else "gl"
        self._first = True

    def update(self, scene: Scene) -> None:
        """The Blender scene now; the GL labels' scene at the next render, on its thread."""
        if self._first and scene is self.bs.scene:
            return
        self._first = False
        self.bs.update(scene)

    def render(self, cam: Camera, then: Callable | None = None, defer: bool = False) -> Rendered:
        """The frame at `cam`, its image always left to Rendered.develop (so `defer` changes
        nothing); `then(depth, instance, silhouettes)`, given, runs on the labels as soon as they
        are drawn and its result is Rendered.labelled: with GL labels beside the path tracer
        (then_seconds 0: it costs the frame no time of its own), with Cycles' after it."""
        if self.rs is None:
            out = self.bs.render(cam, labels=True, develop=False)
            t1 = time.perf_counter()
            labelled = then(out["depth"], out["instance"], partial(self.bs.render_instances, cam)) if then else None
            return Rendered(None, out["depth"], out["instance"], out["seconds"], develop=_image(out["develop"]),
                            labelled=labelled, then_seconds=time.perf_counter() - t1)
        job = self._gl.submit(self._label, self.bs.scene, cam, then)
        try:
            out = self.bs.render(cam, labels=False, develop=False)
        finally:
            wait([job])  # never leave the labels running into the next frame's update
        depth, instance, labelled = job.result()
        return Rendered(None, depth, instance, out["seconds"], develop=_image(out["develop"]), labelled=labelled)

    def _label(self, scene: Scene, cam: Camera, then: Callable | None) -> tuple:
        """On the GL thread: the labels of `scene` at `cam`, and `then` of them."""
        if self.rs.scene is not scene:
            self.rs.update(scene)
        depth, instance = self.rs.labels(cam)
        labelled = then(depth, instance, partial(self.rs.render_instances, cam)) if then else None
        return depth, instance, labelled

    def save_blend(self, path: Path) -> Path:
        """The current frame's Blender scene, camera included, as a .blend a user opens in Blender."""
        return self.bs.save_blend(path)

    def close(self) -> None:
        import shutil

        if self.rs is not None:
            self._gl.submit(self.rs.close).result()
            self._gl.shutdown()
            self.rs, self._gl = None, None
        tmp = getattr(self.bs, "_tmp", None)
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)


def _image(develop: Callable[[], tuple[np.ndarray, float]]) -> Callable[[], np.ndarray]:
    """BlenderScene.render's develop (image and gain) as the image alone."""
    return lambda: develop()[0]


def make_backend(name: str, scene: Scene, quality: str, labels: str = "auto", device: str = "auto"):
    if name == "raster":
        return RasterBackend(scene, quality)
    if name == "cycles":
        return CyclesBackend(scene, quality, labels, device)
    raise ValueError(f"unknown backend {name!r}; choose from {', '.join(BACKENDS)}")


# ---------------------------------------------------------------------------------------------
# The job
# ---------------------------------------------------------------------------------------------


@dataclass
class RenderJob:
    rig: str
    frames: int
    out: Path
    seed: int = 0
    scene: str = "downtown"
    width: int | None = None
    height: int | None = None
    backend: str = "cycles"
    quality: str = "fast"
    start: int = 0
    durable: bool = True
    shard: tuple[int, int] = (1, 1)  # (K, N): this process renders the frames with index % N == K - 1
    overrides: FrameOverrides | None = None  # weather / time of day fixed on the command line
    save_blend: Path | None = None  # Cycles: write the first rendered frame's scene as a .blend
    labels: str = "auto"  # Cycles: depth, ids and silhouettes from GL (auto, gl) or Cycles' own passes
    device: str = "auto"  # Cycles' compute devices (scenes/cycles_devices.py): how frames render, not what
    ahead: bool = True  # run(): may draw each next frame's scene in a second process (Renderer.draw_ahead)
    sequence_length: int = 1  # instants per sequence (1: independent frames, today's render)
    fps: float = DEFAULT_FPS  # instants per second within a sequence

    @property
    def sequences(self) -> bool:
        """Whether the run renders sequences (L > 1) rather than independent frames."""
        return self.sequence_length > 1

    @property
    def cooperative(self) -> bool:
        """Whether several rigs see each instant (`--rig ego,pole,drone`, rigs/meeting.py)."""
        return "," in str(self.rig)

    def __post_init__(self) -> None:
        """Refuse numbers the frames cannot be made from, before anything is written: a seed past
        int64 failed at the first record, after that frame's images were on disk, and a width of 0
        rendered at the rig's width without a word."""
        _within("seed", self.seed, 0, SEED_MAX)
        _within("frames", self.frames, 0, MAX_FRAME_INDEX)
        _within("start", self.start, 0, MAX_FRAME_INDEX)
        if self.start + self.frames - 1 > MAX_FRAME_INDEX:
            raise ValueError(f"the last frame index, start + frames - 1 = {self.start + self.frames - 1}, is past "
                             f"{MAX_FRAME_INDEX} (frame indices are int64); choose a smaller --start")
        for name in ("width", "height"):
            if getattr(self, name) is not None:
                _within(name, getattr(self, name), *RESOLUTION_RANGE)
        _within("sequence-length", self.sequence_length, 1, MAX_SEQUENCE_LENGTH)
        if isinstance(self.fps, bool) or not isinstance(self.fps, numbers.Real) or not FPS_RANGE[0] <= self.fps <= FPS_RANGE[1]:
            raise ValueError(f"--fps {self.fps!r} is outside [{FPS_RANGE[0]:g}, {FPS_RANGE[1]:g}]")
        L = self.sequence_length
        if self.frames % L or self.start % L:
            raise ValueError(f"--frames {self.frames} and --start {self.start} must be multiples of --sequence-length "
                             f"{L} (a run renders whole sequences)")

    def indices(self) -> range:
        """Every frame index of the run (all shards)."""
        return range(self.start, self.start + self.frames)

    def shard_indices(self) -> list[int]:
        """The frame indices this shard renders: whole sequences, sequence q = index // L with
        q % N == K - 1 (round robin on the absolute sequence; with L = 1, on the index), so no two
        shards build the world of one sequence."""
        k, n = self.shard
        return [i for i in self.indices() if (i // self.sequence_length) % n == k - 1]


def _within(name: str, value: int, lo: int, hi: int) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not lo <= value <= hi:
        raise ValueError(f"--{name} {value!r} is outside [{lo}, {hi}]")


def parse_shard(text: str) -> tuple[int, int]:
    """'K/N' (1 <= K <= N) -> (K, N)."""
    try:
        k, n = (int(x) for x in str(text).split("/"))
    except ValueError:
        raise ValueError(f"--shard {text!r}: expected K/N, e.g. 2/8") from None
    if not 1 <= k <= n:
        raise ValueError(f"--shard {text!r}: need 1 <= K <= N")
    return k, n


def scene_name_of(job: RenderJob) -> str:
    """The preset the job's city is drawn from: with a mix (`--scene a,b,c`) the one its seed
    draws (omnigen.scenes.preset.preset_for_seed); a TOML path by its file's stem."""
    from omnigen.scenes.preset import preset_for_seed

    chosen = preset_for_seed(job.scene, job.seed)
    return Path(chosen).stem if chosen.endswith(".toml") else chosen


def render_info(job: RenderJob, rig: Rig | None = None) -> dict:
    """The manifest's `render` entry: the same for every shard and executor of one run. `scene`
    is the preset the city was drawn from; `scene_mix` the mix it was drawn out of, if any."""
    from omnigen.scenes.preset import mix_names

    if job.cooperative:
        return _cooperative_info(job)
    rig = rig or load_rig(job.rig)
    info = {"rig": rig.name, "scene": scene_name_of(job), "seed": job.seed, "backend": job.backend,
            "quality": job.quality, "width": int(job.width or rig.resolution[0]),
            "height": int(job.height or rig.resolution[1])}
    if len(mix_names(job.scene)) > 1:
        info["scene_mix"] = str(job.scene)
    if job.sequences:  # recorded only off the default, so folders rendered before sequences resume as before
        info.update(sequence_length=int(job.sequence_length), fps=float(job.fps))
    return info


def _cooperative_info(job: RenderJob) -> dict:
    """render_info of several rigs: `rigs` the views' labels in the order given (not `rig`, which
    every record's synthetic.rig must equal), the size only when the command line fixes it (else
    each view has its rig's own), sequence_length and fps always."""
    from omnigen.rigs.meeting import views_of
    from omnigen.scenes.preset import mix_names

    info = {"rigs": ",".join(v.label for v in views_of(job.rig)), "scene": scene_name_of(job), "seed": job.seed,
            "backend": job.backend, "quality": job.quality}
    info.update({k: int(v) for k, v in (("width", job.width), ("height", job.height)) if v is not None})
    if len(mix_names(job.scene)) > 1:
        info["scene_mix"] = str(job.scene)
    info.update(sequence_length=int(job.sequence_length), fps=float(job.fps))
    return info


RENDER_ARGS = RENDER_ARGS_FILE
RENDER_FOLDERS = ("records", "images", "depth", "instance")
_FLAGS = {  # recorded key -> how the command line says it (for the refusal's message)
    "rig": "--rig", "rigs": "--rig", "rig_sha256": "the rig's definition (its TOML)", "scene": "--scene",
    "scene_sha256": "the scene preset's definition (its TOML)", "seed": "--seed", "width": "--width",
    "height": "--height", "backend": "--backend", "quality": "--quality", "labels": "--labels",
    "weather": "--weather", "time_of_day": "--time-of-day", "fog_density": "--fog-density",
    "precipitation": "--precipitation", "sequence_length": "--sequence-length", "fps": "--fps",
}


def _sha256_json(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def render_args(job: RenderJob, rig: Rig | None = None, preset=None) -> dict:
    """Every argument that decides a frame's pixels or labels, as recorded in `.render-args.json`.

    Not recorded: --frames, --start and --shard (frame i depends only on (seed, i)), the
    executor, --save-blend, --device (the same frames but for noise on any device, and a cluster
    may resume on nodes of another kind). The rig's and the scene's definitions are hashed, so an edited TOML
    under the same name is a difference too. Quality and label source matter only to Cycles.
    """
    from omnigen.scenes.description import to_dict
    from omnigen.scenes.preset import load_preset, preset_for_seed

    if job.cooperative:
        from omnigen.rigs.meeting import views_of

        rigs = [v.rig for v in views_of(job.rig)]
    else:
        rigs = [rig or load_rig(job.rig)]
    preset = preset if preset is not None else load_preset(preset_for_seed(job.scene, job.seed))
    args = render_info(job, rigs[0])
    rig_fields = [{k: v for k, v in asdict(r).items() if k not in ("description", "source")} for r in rigs]
    rig_fields = rig_fields if job.cooperative else rig_fields[0]
    scene_fields = {k: v for k, v in to_dict(preset).items() if k != "source"}  # where the file lies is no setting
    args.update(rig_sha256=_sha256_json(rig_fields), scene_sha256=_sha256_json(scene_fields))
    if job.backend == "cycles":
        args["labels"] = job.labels
    else:
        args.pop("quality")
    o = job.overrides or FrameOverrides()
    args.update(weather=o.weather, time_of_day=o.time_of_day, fog_density=o.fog_density,
                precipitation=o.precipitation)
    return args


def _recorded_args(out: Path) -> tuple[dict, str] | None:
    """What a render folder says it was rendered with, and where it says so; None for a folder
    with no frames. Folders from before `.render-args.json`: the manifest's `render` entry, else
    the first record (its size, rig, scene and seed)."""
    path = out / RENDER_ARGS
    if path.exists():
        try:  # a regular file of bounded size: a FIFO put there would otherwise hang the render
            return json.loads(read_regular(path, MANIFEST_MAX_BYTES)), str(path)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"{path}: not valid JSON ({exc}); delete the folder or rerun with --fresh") from None
    render = read_manifest(out).get("render") if (out / MANIFEST).exists() else None
    if render:
        return dict(render), str(out / MANIFEST)
    records = sorted((out / RECORDS_DIR).glob("synthetic-*.json")) if (out / RECORDS_DIR).is_dir() else []
    if not records:
        return None
    r = json.loads(read_regular(records[0], MANIFEST_MAX_BYTES))
    if not isinstance(r, dict):
        raise ValueError(f"{records[0]}: not a record (a JSON object); delete the folder or rerun with --fresh")
    syn = r.get("synthetic") if isinstance(r.get("synthetic"), dict) else {}
    return {"width": r.get("width"), "height": r.get("height"), "rig": syn.get("rig"), "scene": syn.get("scene"),
            "seed": syn.get("seed")}, str(records[0])


def claim_render_folder(job: RenderJob, args: dict) -> None:
    """Record `args` in the folder, or refuse a folder whose frames were rendered with others.

    Shards and Ray actors of one run all call this: equal arguments write equal bytes, atomically.
    """
    out = Path(job.out)
    recorded = _recorded_args(out)
    if recorded is not None:
        was, where = recorded
        # the recorded file names every argument; an older folder's manifest or record only some
        if where.endswith(RENDER_ARGS):
            keys = [k for k in _FLAGS if k in was or k in args]
        else:
            keys = [k for k in _FLAGS if k in was and k in args]
        diff = [k for k in keys if was.get(k) != args.get(k)]
        if diff:
            said = "; ".join(f"{_FLAGS[k]}: {_shown(was.get(k))} there, {_shown(args.get(k))} now" for k in diff)
            raise ValueError(f"{out}: its frames were rendered with other arguments ({said}; recorded in {where}); "
                             "rerun with the same arguments to resume, choose another --out, or add --fresh to "
                             "delete its frames and start over")
    if not (out / RENDER_ARGS).exists():
        atomic_write_json(out / RENDER_ARGS, args, indent=2)


def _shown(v) -> str:
    if isinstance(v, str) and len(v) == 64:  # a definition's hash
        return v[:12]
    return "unset" if v is None else str(v)


def start_over(out: str | Path) -> int:
    """--fresh: delete a render folder's frames, index, manifest and recorded arguments; the
    number of records deleted. Only a folder that is a render's (recorded arguments, a manifest
    with a `render` entry, or only rendered records) is touched; anything else is refused."""
    out = Path(out)
    if not out.exists():
        return 0
    recorded = (out / RENDER_ARGS).exists() or "render" in (read_manifest(out) if (out / MANIFEST).exists() else {})
    records = list((out / RECORDS_DIR).glob("*.json")) if (out / RECORDS_DIR).is_dir() else []
    if not recorded and (not records or not all(p.name.startswith("synthetic-") for p in records)):
        if any(out.iterdir()):
            raise ValueError(f"{out}: --fresh deletes only a render's frames, and this folder is no render "
                             "folder (no .render-args.json, no render manifest); choose another --out")
        return 0
    (out / MANIFEST).unlink(missing_ok=True)  # unsealed first
    (out / INDEX_FILE).unlink(missing_ok=True)
    for sub in RENDER_FOLDERS:
        shutil.rmtree(out / sub, ignore_errors=True)
    (out / RENDER_ARGS).unlink(missing_ok=True)  # last: a kill before this leaves a folder --fresh still knows
    return len(records)


def view_labels(job: RenderJob, rig: Rig | None = None) -> list[str]:
    """The labels frame ids are made of: the rig's name, or each view's (rigs/meeting.py)."""
    if job.cooperative:
        from omnigen.rigs.meeting import views_of

        return [v.label for v in views_of(job.rig)]
    return [(rig or load_rig(job.rig)).name]


def missing_frames(job: RenderJob, rig: Rig | None = None) -> list[int]:
    """Indices (instants) of the run (all shards) of which some view's record is not written yet."""
    labels = view_labels(job, rig)
    records = Path(job.out) / "records"
    return [i for i in job.indices()
            if not all((records / f"{frame_id_for(label, job.seed, i)}.json").exists() for label in labels)]


def finalize_run(job: RenderJob, show_progress: bool = True, writer: DatasetWriter | None = None) -> bool:
    """Build the index and manifest once every frame of the run has its record; False (nothing
    written) while any is missing. The manifest depends only on records/ and `render_info`, so
    shards that finalize at the same time write the same bytes, each atomically."""
    rig = None if job.cooperative else load_rig(job.rig)
    if missing_frames(job, rig):
        return False
    claim_render_folder(job, render_args(job, rig))  # --finalize-only with other arguments is refused too
    writer = writer or DatasetWriter(job.out, durable=job.durable)
    writer.finalize({"render": render_info(job, rig)}, show_progress=show_progress)
    return True


FrameFiles = tuple[tuple[str, "np.ndarray | Callable[[], np.ndarray]"], tuple[str, np.ndarray], tuple[str, np.ndarray]]


def _frame_files(record: FrameRecord, rgb: np.ndarray | Callable[[], np.ndarray], out: Rendered) -> FrameFiles:
    """A frame's files as the writer takes them: (path under the render folder, array) for the
    image, depth and instance mask, the paths as its record names them. `rgb` apart from `out`:
    a deferred render's image is read back later (Rendered.finish), and a Cycles image is
    developed by the writer (a function, Rendered.develop)."""
    return ((record.image, rgb), (record.synthetic.depth, out.depth), (record.synthetic.instance, out.instance))


@dataclass
class RenderSummary:
    rendered: int = 0
    skipped: int = 0
    objects: int = 0
    redraws: int = 0
    seconds: float = 0.0
    failed: list[int] = field(default_factory=list)  # frames given up after the retries (Ray executor)
    finalized: bool = False  # False: other shards' frames are still missing (or frames failed)
    timings: dict[str, float] = field(default_factory=lambda: {"scene": 0.0, "camera": 0.0, "render": 0.0,
                                                               "annotate": 0.0, "write": 0.0, "build": 0.0,
                                                               "renderer_core": 0.0})


def first_camera(rig: Rig, width: int, height: int, scene: Scene) -> tuple[DrawnCamera, np.random.Generator]:
    """A frame's first camera draw (sample_camera from the rig's own stream of the frame) and that
    stream as the draw left it, which a redraw goes on with: a function of the scene alone, so a
    FramesAhead worker makes it with the scene (its `then`) and this process need not."""
    rng = rig_rng(scene.dataset_seed, scene.frame_index)
    return sample_camera(rig, scene, rng, width, height, Obstacles(scene)), rng


def _at(placed: DrawnCamera | Ride, scene: Scene) -> tuple[DrawnCamera, int | None]:
    """A sequence view's camera at `scene`'s instant and the track of the car it rides (None
    for a held camera)."""
    if isinstance(placed, Ride):
        return placed.at(scene), placed.track
    return placed, None


def camera_to_world(cam: DrawnCamera) -> np.ndarray:
    """The record's camera_to_world, [[R^T, position], [0 0 0 1]]: X_cam = R X_world + t with
    t = -R position, so X_world = R^T X_cam + position, in the scene's world (z up, ground z = 0)."""
    m = np.eye(4)
    m[:3, :3] = cam.R.T
    m[:3, 3] = cam.position
    return m


class Renderer:
    """Holds the city, the backend and the rig; renders frames by index. Build once per process."""

    def __init__(self, job: RenderJob) -> None:
        from omnigen.scenes.generate import SceneGenerator

        if job.backend not in BACKENDS:
            raise ValueError(f"unknown backend {job.backend!r}; choose from {', '.join(BACKENDS)}")
        if job.quality not in QUALITIES:
            raise ValueError(f"unknown quality {job.quality!r}; choose from {', '.join(QUALITIES)}")
        self.job = job
        from omnigen.rigs.meeting import views_of

        self.views = views_of(job.rig) if job.cooperative else []  # several rigs: each instant from each
        self.rig: Rig = self.views[0].rig if self.views else load_rig(job.rig)
        self.width = int(job.width or self.rig.resolution[0])
        self.height = int(job.height or self.rig.resolution[1])
        self.gen = SceneGenerator(job.scene, job.seed)  # a mix: the preset the seed draws
        self.scene_name = scene_name_of(job)
        self.backend = None
        self._blend_saved = False
        claim_render_folder(job, render_args(job, None if self.views else self.rig, self.gen.preset))  # before any frame is written
        self.writer = DatasetWriter(job.out, durable=job.durable)
        self.summary = RenderSummary()
        # Write-behind (run() turns it on): a frame's files are encoded and written on a thread
        # while the next frame is drawn. Why: PNG and EXR compression release the GIL and the
        # scene stage is single-threaded Python, so on a second core the writing costs the frame
        # rate next to nothing. At most one frame's writing is pending (flush() waits for it); a
        # frame's record is still written after its images, so a killed run leaves no record
        # without its files. Off, render_frame returns with the frame on disk (Ray actors, tests).
        # With write-behind the raster backend's colour pass is also left to finish while the next
        # frame's scene and first camera are drawn (pure Python, on one core, while llvmpipe shades
        # on its threads): it is started once annotation has kept the camera (a rejected camera is
        # never shaded) and read back before the next frame's backend update, or by flush().
        self.write_behind = False
        self._pending: Future | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._unfinished: tuple[Rendered, FrameRecord] | None = None  # a deferred frame, its image to read back
        self.ahead: FramesAhead | None = None  # run(): the next frame's scene drawn in a second process
        self._sequence: tuple | None = None  # sequences: (q, World, camera) of the sequence rendered last

    def frame_id(self, index: int) -> str:
        return frame_id_for(self.rig.name, self.job.seed, index)

    def render_frame(self, index: int, next_index: int | None = None) -> FrameRecord:
        """Render, annotate and write frame `index`; returns its record. `next_index`: the frame
        rendered next, whose scene is drawn meanwhile when frames are drawn ahead (`self.ahead`)."""
        job, tm = self.job, self.summary.timings
        if job.sequences:  # no stream: a sequence's camera is never redrawn (_instant)
            scene, placed = self._instant(index)
            cam, own = _at(placed, scene)
            return self._render_view(scene, cam, None, self.rig, self.frame_id(index), index, own)
        if self.ahead is not None and next_index is not None:
            self.ahead.ask(job.seed, next_index, job.overrides)
        t0 = time.perf_counter()
        scene, drawn = self.ahead.frame_with(job.seed, index, job.overrides) if self.ahead is not None \
            else (self.gen.frame(job.seed, index, job.overrides), None)
        tm["scene"] += time.perf_counter() - t0
        # The first camera is drawn (pure Python) with the scene in the worker, else here while the
        # previous frame may still be shaded; its stream goes on for a redraw.
        t1 = time.perf_counter()
        cam, rng = drawn if drawn is not None else first_camera(self.rig, self.width, self.height, scene)
        tm["camera"] += time.perf_counter() - t1
        return self._render_view(scene, cam, rng, self.rig, self.frame_id(index), index)

    def _render_view(self, scene: Scene, cam: DrawnCamera, rng: np.random.Generator | None, rig: Rig, fid: str,
                     index: int, own: int | None = None) -> FrameRecord:
        """Render, annotate and write one view of a scene; `rng`: the stream a redraw goes on
        with (None: the camera is kept whatever the render counts, as in sequences); `own`: the
        track of the car the camera rides, never an object of its own view (it stands behind
        the camera: a guard against a sliver past the near plane)."""
        job, tm = self.job, self.summary.timings
        width, height = cam.width, cam.height
        self._finish_frame()  # the previous frame's image, shaded while this frame's scene and camera were drawn
        t1 = time.perf_counter()
        if self.backend is None:
            self.backend = make_backend(job.backend, scene, job.quality, job.labels, job.device)
            tm["build"] += time.perf_counter() - t1
        else:
            self.backend.update(scene)
            tm["scene"] += time.perf_counter() - t1
        obstacles = None  # a redraw's, built at the first one
        while True:
            t3 = time.perf_counter()
            out = self.backend.render(cam, then=partial(annotate, scene, cam), defer=self.write_behind)
            t2 = time.perf_counter()
            tm["render"] += t2 - t3 - out.then_seconds
            tm["renderer_core"] += out.render_seconds
            tm["annotate"] += out.then_seconds
            ann = out.labelled
            if rng is None or len(ann.objects) >= rig.min_objects or cam.tries >= rig.max_tries:
                break
            self.summary.redraws += 1
            obstacles = obstacles or Obstacles(scene)
            cam = sample_camera(rig, scene, rng, width, height, obstacles, start_try=cam.tries)
            tm["camera"] += time.perf_counter() - t2
        if out.shade is not None:  # the kept camera's colour pass, shaded while the next scene and camera are drawn
            t = time.perf_counter()
            out.shade()
            self._charge(t, "render", "renderer_core")
        t5 = time.perf_counter()
        image, depth, instance = f"images/{fid}.png", f"depth/{fid}.exr", f"instance/{fid}.png"
        plane = cam.ground_plane
        record = FrameRecord(
            frame_id=fid, source="synthetic", view=rig.view, image=image, width=width, height=height,
            K=cam.K, objects=[o for o in ann.objects if own is None or o.track_id != own],
            ignore_regions=ann.ignore_regions, ground_plane=plane,
            camera_height=plane.camera_height, camera_pitch=plane.camera_pitch,
            group=f"synthetic-{self.scene_name}-{job.seed}", camera_to_world=camera_to_world(cam),
            **self._sequence_fields(index),
            synthetic=SyntheticInfo(seed=job.seed, scene=self.scene_name, rig=rig.name,
                                    weather=to_dict(scene.weather), lighting=to_dict(scene.lighting),
                                    depth=depth, instance=instance),
        )
        if out.finish is not None:
            self._unfinished = (out, record)
        elif self.write_behind:
            self._submit(_frame_files(record, out.develop or out.rgb, out), record)
        else:
            self._write_frame(_frame_files(record, out.develop or out.rgb, out), record)
        if job.save_blend is not None and not self._blend_saved:
            self.backend.save_blend(job.save_blend)
            self._blend_saved = True
        tm["write"] += time.perf_counter() - t5
        self.summary.rendered += 1
        self.summary.objects += len(record.objects)
        return record

    def _instant(self, index: int) -> tuple[Scene, DrawnCamera | Ride]:
        """Instant k = index % L of sequence q = index // L: the sequence's World at time k / fps,
        and its camera, drawn once at instant 0 (the rig's stream of frame q) and held for the
        whole sequence, or for an ego rig the car it rides (`_ride_or`). No stream goes with it: a
        sequence's camera is never redrawn after a render, since a process resuming mid-sequence
        could not know of that redraw; it is kept on sample_camera's geometric checks alone. Both
        are rebuilt for any sequence not held, so a resumed run equals an uninterrupted one."""
        from omnigen.rigs.meeting import View

        view = View(self.rig.name, self.rig, 1)
        return self._held(index, lambda world, q: self._ride_or(
            view, world, q, self.width, self.height, lambda: first_camera(self.rig, self.width, self.height,
                                                                          world.scene0)[0]))

    def _ride_or(self, view, world, q: int, width: int, height: int, held: Callable):
        """An ego view's Ride on the car approaching the sequence's junction, else `held()`: the
        view's camera held for the sequence (every other kind of view). Choosing the car reads the
        sequence's last instant, so its motion is stepped to the end here and again instant by
        instant as the views render: a second pass of the motion, cheap beside the renders, where
        keeping every step's state would make a sequence's memory grow with its length."""
        from omnigen.rigs.meeting import meeting_junction, place_ego_ride

        if view.rig.view != "ego":
            return held()
        last = world.scene_at(self.job.sequence_length - 1, self.job.fps)
        ride = place_ego_ride(view, world.scene0, last, meeting_junction(world.scene0), self.job.seed, q, width, height)
        return ride if ride is not None else held()

    def _held(self, index: int, place: Callable) -> tuple[Scene, object]:
        """The Scene of instant `index` of its sequence's World, and `place(world, q)` (the
        sequence's cameras), both made once per sequence and held for its instants."""
        from omnigen.scenes.world import World

        job, tm = self.job, self.summary.timings
        q, k = divmod(index, job.sequence_length)
        t0 = time.perf_counter()
        if self._sequence is None or self._sequence[0] != q:
            world = World.build(self.gen.city, self.gen.preset, job.seed, q, job.overrides, self.gen.user_assets)
            t1 = time.perf_counter()
            tm["scene"] += t1 - t0
            placed = place(world, q)
            t0 = time.perf_counter()
            tm["camera"] += t0 - t1
            self._sequence = (q, world, placed)
        _, world, placed = self._sequence
        scene = world.scene_at(k, job.fps)
        tm["scene"] += time.perf_counter() - t0
        return scene, placed

    def render_instant(self, index: int) -> list[FrameRecord]:
        """Several rigs: instant `index` (k = index % L of sequence q = index // L) from every view
        whose record is not written yet, all from one Scene of the sequence's World; the views are
        placed once per sequence around one junction (rigs/meeting.py) and held."""
        scene, cams = self._held(index, self._place_views)
        records = []
        for v, placed in zip(self.views, cams):
            fid = frame_id_for(v.label, self.job.seed, index)
            if not self.writer.has(fid):  # a resumed instant: only its missing views
                cam, own = _at(placed, scene)
                records.append(self._render_view(scene, cam, None, v.rig, fid, index, own))
        return records

    def _place_views(self, world, q: int) -> list[DrawnCamera | Ride]:
        """Every view's camera of sequence q, around the junction the sequence draws; an ego
        view rides its car where there is one."""
        from omnigen.rigs.meeting import meeting_junction, place_view

        job, scene0 = self.job, world.scene0
        junction, obstacles = meeting_junction(scene0), Obstacles(scene0)
        placed = []
        for v in self.views:
            w, h = int(job.width or v.rig.resolution[0]), int(job.height or v.rig.resolution[1])
            placed.append(self._ride_or(v, world, q, w, h,
                                        lambda v=v, w=w, h=h: place_view(v, scene0, junction, job.seed, q, w, h,
                                                                         obstacles)))
        return placed

    def _sequence_fields(self, index: int) -> dict:
        """A record's `sequence` and `timestamp`: none for independent frames of one rig (L = 1);
        views of one instant of several rigs always share both."""
        job = self.job
        if not (job.sequences or job.cooperative):
            return {}
        q, k = divmod(index, job.sequence_length)
        return {"sequence": sequence_id_for(self.scene_name, job.seed, q), "timestamp": k / float(job.fps)}

    def draw_ahead(self, frames: int) -> bool:
        """Draw each next frame's scene in a second process (FramesAhead) from now on, if the job
        allows it, a run of `frames` frames repays the worker's start (AHEAD_MIN_FRAMES) and two
        cores or more may run it; whether frames are drawn ahead. Ray actors never do: each has
        its one CPU. Nor do sequences (L > 1): an instant's scene is the World's rollout, drawn
        here, and a sequence's instant 0 is built once per L instants."""
        if self.ahead is None and self.job.ahead and not self.job.sequences and frames >= AHEAD_MIN_FRAMES and len(os.sched_getaffinity(0)) >= 2:
            self.ahead = FramesAhead(self.gen, meshes=self.job.backend == "cycles",  # Cycles builds every agent
                                     then=partial(first_camera, self.rig, self.width, self.height))
        return self.ahead is not None

    def _write_frame(self, files: FrameFiles, record: FrameRecord) -> None:
        """A frame's image, depth and instance mask, each atomically, then its record (last: a
        frame whose record exists is complete)."""
        root, durable = Path(self.job.out), self.job.durable
        (image, rgb), (depth, z), (instance, ids) = files
        if callable(rgb):  # a Cycles image, developed here: on the writer's thread with write-behind
            rgb = rgb()
        atomic_write_bytes(root / image, png_bytes(rgb), durable=durable)
        write_depth_exr(root / depth, z)
        atomic_write_bytes(root / instance, png_bytes(ids), durable=durable)
        self.writer.write(record)

    def _finish_frame(self) -> None:
        """Read back the deferred image of the last frame rendered, if any, and hand its files to
        the writer (the wait for the shading counts as render time)."""
        held, self._unfinished = self._unfinished, None
        if held is None:
            return
        out, record = held
        t0 = time.perf_counter()
        rgb = out.finish()
        self._charge(t0, "render", "renderer_core")
        self._submit(_frame_files(record, rgb, out), record)

    def _charge(self, since: float, *stages: str) -> None:
        """Add the time since `since` to each of `stages` (one reading of the clock for all: the
        raster colour pass is both render time and the renderer's own work)."""
        took = time.perf_counter() - since
        for stage in stages:
            self.summary.timings[stage] += took

    def _submit(self, files: FrameFiles, record: FrameRecord) -> None:
        """Queue a frame's files for the writer thread, after the previous frame's are written."""
        self._wait_for_writes()
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="omnigen-write")
        self._pending = self._pool.submit(self._write_frame, files, record)

    def _wait_for_writes(self) -> None:
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def flush(self) -> None:
        """Wait until every frame rendered so far is on disk (write-behind); a failed write raises here."""
        self._finish_frame()
        self._wait_for_writes()

    def run(self, show_progress: bool = True) -> RenderSummary:
        from omnigen.progress import progress

        start = time.perf_counter()
        job = self.job
        indices = job.shard_indices()
        labels = [v.label for v in self.views] or [self.rig.name]
        todo = [i for i in indices if not all(self.writer.has(frame_id_for(b, job.seed, i)) for b in labels)]
        self.summary.skipped = len(indices) - len(todo)
        self.write_behind = True
        if not self.views:
            self.draw_ahead(len(todo))
        try:
            for k, i in enumerate(progress(todo, desc=f"render {job.rig if self.views else self.rig.name}", disable=not show_progress, unit="frame")):
                if self.views:
                    self.render_instant(i)
                else:
                    self.render_frame(i, todo[k + 1] if k + 1 < len(todo) else None)
        finally:
            self.close()
        # The last shard to finish finds every frame written and finalizes (see finalize_run).
        self.summary.finalized = finalize_run(job, show_progress, self.writer)
        self.summary.seconds = time.perf_counter() - start
        return self.summary

    def close(self) -> None:
        """Flush pending writes, then free the backend and the frames' worker (also when a write failed)."""
        try:
            self.flush()
        finally:
            if self.ahead is not None:
                self.ahead.close()
                self.ahead = None
            if self._pool is not None:
                self._pool.shutdown()
                self._pool = None
            if self.backend is not None:
                self.backend.close()
                self.backend = None
