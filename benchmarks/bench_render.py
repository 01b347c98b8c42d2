"""`omnigen render` speed: raster frames/s and Cycles seconds per frame at 640x640, and the overhead share.

Renders the default city (downtown) from the drone rig into a temporary folder with the real
pipeline (scene re-randomisation, camera, render, annotation, atomic writes) and prints, per
backend: frames, seconds per frame (the one-off city/backend build excluded and shown apart),
frames per second, time by stage, and the overhead share: the fraction of the per-frame time not
spent in the renderer's own core (Cycles' beauty path tracing; for raster the whole pyrender call
counts as the core). Resident memory is printed after the first and the last frame. Frames are
written as `omnigen render` writes them: each frame's files on a thread while the next is drawn
(the "write" stage is the time the loop waited for them; the last frame's writing is in the total),
and each next frame's scene drawn in a second process where `omnigen render` would (the "scene"
stage is then the wait for it and the backend's update).

What it is held to on a 2-core machine (docs/rendering-speed.md): at most 25% of a raster frame
outside the renderer core; Cycles --quality fast at most 5% outside the path tracer and a scene
stage of at most 0.5 s; resident memory after frame 200 within 10% of frame 20's
(`--memory-frames 200 --memory-backend raster,cycles`). Frames per second and seconds per frame
are the machine's: they are printed, not held to a figure.

`--coop N` instead renders N instants of a cooperative raster sequence (`--rig ego,pole,drone`,
sequences of `--coop-length` instants, 10 fps) as `omnigen render` does, and in the same run, in
alternating rounds, as many drone frames of the same size (3N independent frames): seconds per
view-frame of each and their ratio (issue 46: at most 1.2), the cooperative stage split, the share
of track-instants seen by two views or more, and each one's one-off build apart. With
`--memory-instants M`, resident memory every `--memory-every` instants of a long cooperative run
and its change from the first reading to the last (within 10% over 1,000 instants).

`--profile` instead prints, per backend and per preset (PROFILE_PRESETS), where the time of the
frames after frame 0 goes: the stage timers, and the parts of each stage root of PROFILE_ROOTS
(drawing the frame's Scene, updating the backend, drawing the camera, building the raster's agent
buffers, annotating) split by the functions they call, from cProfile's call graph (which slows
Python code, not the renderers: compare parts with each other, not with the plain stage rows). A
Cycles frame's GL labels and annotation run on their own thread beside the path tracer, which
this thread's profile does not see.
`--profile-clock cpu` times the parts by the rendering thread's CPU time, for a loaded machine;
`--profile-ahead` draws each next scene (and for Cycles its agent meshes) in a second process, as
a run of 16 frames or more does, so the parts are what the render process is left with.

    .venv/bin/python benchmarks/bench_render.py [--raster-frames 21] [--cycles-frames 21] [--size 640] [--no-cycles]
        [--no-raster] [--memory-frames 200 [--memory-backend raster,cycles] [--memory-size 96] [--memory-quality preview]]
    .venv/bin/python benchmarks/bench_render.py --coop 30 [--coop-length 10] [--coop-rounds 5] [--size 640] [--scene downtown]
        [--memory-instants 1000 [--memory-size 96] [--memory-every 100]]
    .venv/bin/python benchmarks/bench_render.py --profile [--profile-frames 4] [--size 640] [--quality fast] [--no-cycles]
        [--no-raster] [--profile-presets downtown,intersection,suburban] [--profile-clock wall|cpu] [--profile-ahead]
"""

from __future__ import annotations

import argparse
import cProfile
import platform
import pstats
import re
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def backends(text: str) -> list[str]:
    """A comma-separated list of raster and cycles (--memory-backend)."""
    names = [t.strip() for t in text.split(",") if t.strip()]
    if not names or any(n not in ("raster", "cycles") for n in names):
        raise argparse.ArgumentTypeError(f"{text!r}: raster, cycles or raster,cycles")
    return names


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


def drone_renderer(out: Path, backend: str, frames: int, size: int, quality: str, scene: str, seed: int):
    """A Renderer of frames 0..frames-1 of the drone rig over `scene` into `out`, writing as
    `omnigen render` (Renderer.run) writes: each frame's files on a thread while the next is drawn."""
    from omnigen.rigs.render import RenderJob, Renderer

    r = Renderer(RenderJob(rig="drone", frames=frames, out=out, seed=seed, scene=scene, width=size, height=size,
                           backend=backend, quality=quality, durable=False))
    r.write_behind = True
    return r


def render_frames(r, indices: range) -> dict[str, float]:
    """Render `indices` as Renderer.run does (each told the job's next index, which a renderer
    drawing ahead asks its worker for) and wait for their files (the last frame's writing is part
    of the time); the seconds each stage of the summary's timings took over them."""
    base = dict(r.summary.timings)
    job_indices = r.job.indices()
    for i in indices:
        r.render_frame(i, i + 1 if i + 1 in job_indices else None)
    r.flush()
    return {k: v - base[k] for k, v in r.summary.timings.items()}


def bench(backend: str, frames: int, size: int, quality: str, scene: str, seed: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        r = drone_renderer(Path(tmp) / backend, backend, frames, size, quality, scene, seed)
        ahead = r.draw_ahead(frames)  # each next frame's scene drawn in a second process where `omnigen render` would
        t0 = time.perf_counter()
        render_frames(r, range(1))
        first = time.perf_counter() - t0
        rss_first = rss_mb()
        build = r.summary.timings["build"]
        bs = getattr(r.backend, "bs", None)  # Cycles' Blender scene
        before = bs.agent_mesh_counts() if bs is not None else {}
        t1 = time.perf_counter()
        tm = render_frames(r, range(1, frames))
        loop = time.perf_counter() - t1
        rss_last = rss_mb()
        meshes = {k: n - before[k] for k, n in bs.agent_mesh_counts().items()} if bs is not None else None
        r.close()
    n = frames - 1
    core = tm["renderer_core"]
    return {"backend": backend, "frames": n, "s_per_frame": loop / n, "fps": n / loop, "first_frame_s": first,
            "build_s": build, "core_s_per_frame": core / n, "overhead_share": 1 - core / loop,
            "stages": {k: v / n for k, v in tm.items() if k not in ("build",)}, "rss_first": rss_first,
            "rss_last": rss_last, "objects": r.summary.objects, "redraws": r.summary.redraws, "ahead": ahead,
            "agent_meshes": meshes}


def report(res: dict) -> None:
    from omnigen.progress import print_table

    rows = [["frames timed (after frame 0)", res["frames"]],
            ["seconds per frame", round(res["s_per_frame"], 3)],
            ["frames per second", round(res["fps"], 2)],
            ["renderer core, s per frame", round(res["core_s_per_frame"], 3)],
            ["overhead share (not core)", f"{100 * res['overhead_share']:.1f}%"],
            ["frame 0 incl. build, s", round(res["first_frame_s"], 2)],
            ["city + backend build, s", round(res["build_s"], 2)],
            ["objects annotated (all frames)", res["objects"]],
            ["camera redraws after annotation", res["redraws"]],
            ["scenes drawn ahead (second process)", "yes" if res["ahead"] else "no"],
            ["resident MB after frame 0", round(res["rss_first"])],
            ["resident MB after last frame", round(res["rss_last"])]]
    if res["agent_meshes"] is not None:
        per = {k: n / res["frames"] for k, n in res["agent_meshes"].items()}
        rows.append(["agent meshes moved / built, per frame", f"{per['moved']:.1f} / {per['built']:.1f}"])
    rows += [[f"  stage {k}, s per frame", round(v, 3)] for k, v in res["stages"].items()]
    print_table(f"{res['backend']}: drone rig", ["measure", "value"], rows)


PROFILE_PRESETS = ("downtown", "intersection", "suburban")
PROFILE_ROOTS = (  # (row label, file name, function, levels of callees shown)
    ("scene: SceneGenerator.frame", "generate.py", "randomize_frame", 2),
    ("scene: backend.update", "render.py", "update", 3),  # RasterBackend.update or CyclesBackend.update
    ("camera: sample_camera", "sampling.py", "sample_camera", 1),
    ("render: raster agent buffers", "raster_backend.py", "_prepare_agents", 1),  # raster only (Cycles: see below)
    ("annotate", "annotate.py", "annotate", 1),
)
PROFILE_MIN_SHARE = 0.02  # a callee under this share of its stage root's time is folded into "other"
PROFILE_STAGES = ("scene", "camera", "render", "annotate", "write")
_INLINE = ("<genexpr>", "<listcomp>", "<dictcomp>", "<setcomp>", "<lambda>")  # their callees shown in their place

Func = tuple[str, int, str]  # cProfile's key of a function: (file, first line, name)


def _label(func: Func, caller: Func | None = None) -> str:
    """A function as a row names it: `module.function`, just `function` under a caller of the
    same module, a builtin or C method by its own name and "(C)"."""
    file, _, name = func
    if file == "~":
        m = re.search(r"'([^']+)'", name) or re.search(r"method (\S+)>", name)
        return (m.group(1) if m else name).split(".")[-1] + " (C)"
    return name if caller is not None and caller[0] == file else f"{Path(file).stem}.{name}"


def call_tree(stats: pstats.Stats, file: str, name: str, depth: int, frames: int) -> dict[tuple[str, ...], tuple[float, float]]:
    """(seconds, calls) per frame of the function `name` in `file` and of its callees down to
    `depth` levels, keyed by the path of labels from it. Comprehensions and lambdas, and builtins
    that only call them (list.extend over a generator), are looked through: their callees count as
    their caller's. A callee under PROFILE_MIN_SHARE of the root's time is folded into its caller's
    "other" row (the caller's own time and small callees). cProfile keeps one level of callers, so
    the callees of a function called from several places are given to each place in proportion to
    its share of that function's time."""
    table = stats.stats  # func -> (primitive calls, calls, own time, cumulative time, {caller: edge})
    children: dict[Func, list[tuple[Func, tuple]]] = {}
    for func, (*_, callers) in table.items():
        for caller, edge in callers.items():
            children.setdefault(caller, []).append((func, edge))
    roots = [f for f in table if Path(f[0]).name == file and f[2] == name]
    if not roots:
        return {}
    total = sum(table[f][3] for f in roots)
    root = (name if len(roots) > 1 else _label(roots[0]),)
    out = {root: (total / frames, sum(table[f][1] for f in roots) / frames)}
    floor = PROFILE_MIN_SHARE * total

    def callees(funcs: list[Func], share: float, seen: frozenset, edges: dict) -> dict[Func, list[float]]:
        """Each callee's (seconds, calls) from `funcs`, `share` of whose time is this path's."""
        for f in funcs:
            for g, (_, nc, _, ct) in children.get(f, []):
                if g in seen:
                    continue
                if g[2] in _INLINE or (g[0] == "~" and children.get(g) and all(c[2] in _INLINE for c, _ in children[g])):
                    callees([g], share * ct / max(table[g][3], 1e-12), seen | {g}, edges)
                    continue
                e = edges.setdefault(g, [0.0, 0.0])
                e[0], e[1] = e[0] + share * ct, e[1] + share * nc
        return edges

    def walk(funcs: list[Func], path: tuple[str, ...], spent: float, level: int, seen: frozenset) -> None:
        edges = callees(funcs, spent / max(sum(table[f][3] for f in funcs), 1e-12), seen, {})
        shown = 0.0
        for g, (ct, nc) in sorted(edges.items(), key=lambda kv: -kv[1][0]):
            if ct < floor:
                continue
            shown += ct
            sub = path + (_label(g, funcs[0]),)
            out[sub] = (ct / frames, nc / frames)
            if level > 1:
                walk([g], sub, ct, level - 1, seen | {g})
        if shown and spent - shown >= floor:
            out[path + ("other",)] = ((spent - shown) / frames, 0.0)

    walk(roots, root, total, depth, frozenset(roots))
    return out


PROFILE_CLOCKS = {"wall": time.perf_counter, "cpu": time.thread_time}


def profile_frames(backend: str, scene: str, frames: int, size: int, quality: str, seed: int = 0, clock: str = "wall",
                   ahead: bool = False):
    """Render frames 0..frames-1 of the drone rig over `scene` as `omnigen render` does, but for
    drawing every scene in this process (what a run of under AHEAD_MIN_FRAMES frames does, so
    the profile sees its parts; with `ahead`, in a second process as a longer run does, so the
    profile sees what is left to the render process: for Cycles, no agent mesh is built there),
    profiling every frame after frame 0 (the city and backend build) by `clock` (PROFILE_CLOCKS;
    "cpu": the rendering thread's CPU time, what a loaded machine still measures); (pstats.Stats,
    stage wall seconds per frame)."""
    from omnigen.rigs.render import AHEAD_MIN_FRAMES

    with tempfile.TemporaryDirectory() as tmp:
        r = drone_renderer(Path(tmp), backend, frames, size, quality, scene, seed)
        if ahead:
            r.draw_ahead(max(frames, AHEAD_MIN_FRAMES))
        try:
            render_frames(r, range(1))
            prof = cProfile.Profile(PROFILE_CLOCKS[clock])
            prof.enable()
            tm = render_frames(r, range(1, frames))
            prof.disable()
        finally:
            r.close()
    return pstats.Stats(prof), {k: tm[k] / (frames - 1) for k in PROFILE_STAGES}


def profile_rows(results: dict[str, tuple[pstats.Stats, dict]], frames: int) -> list[list]:
    """One row per stage and per part of PROFILE_ROOTS, a column per preset: milliseconds per
    frame, and the calls per frame of a part in brackets."""
    presets = list(results)
    rows = [[f"stage {k} (wall)"] + [f"{1000 * results[p][1][k]:.1f}" for p in presets] for k in PROFILE_STAGES]
    for label, file, name, depth in PROFILE_ROOTS:
        trees = {p: call_tree(results[p][0], file, name, depth, frames - 1) for p in presets}
        paths: list[tuple[str, ...]] = []
        for p in presets:
            paths += [path for path in trees[p] if path not in paths]
        if not paths:
            continue
        weight = {path: sum(trees[p].get(path, (0.0, 0.0))[0] for p in presets) for path in paths}
        # depth first, the heavier sibling first, "other" after its siblings
        for path in sorted(paths, key=lambda q: [(q[k] == "other", -weight.get(q[:k + 1], 0.0), q[k]) for k in range(len(q))]):
            cells = []
            for p in presets:
                sec, calls = trees[p].get(path, (0.0, 0.0))
                shown = f"{calls:.1f}".rstrip("0").rstrip(".")
                cells.append(f"{1000 * sec:.1f}" + (f" ({shown})" if calls >= 0.05 and len(path) > 1 else ""))
            rows.append([label if len(path) == 1 else "  " * (len(path) - 1) + path[-1]] + cells)
    return rows


def profile(backend: str, frames: int, size: int, quality: str, presets=PROFILE_PRESETS, seed: int = 0,
            clock: str = "wall", ahead: bool = False) -> None:
    from omnigen.progress import print_table

    results = {p: profile_frames(backend, p, frames, size, quality, seed, clock, ahead) for p in presets}
    where = "; scenes drawn ahead in a second process" if ahead else ""
    print_table(f"{backend}: where a frame's time goes (drone rig, {size}x{size}, {quality}; ms per frame over frames "
                f"1-{frames - 1}, parts by {clock} clock, calls per frame in brackets{where})", ["part"] + list(presets),
                profile_rows(results, frames))


def memory(backend: str, frames: int, size: int, scene: str, seed: int, quality: str = "preview") -> None:
    """Resident memory every 10 frames over a long run (leaks show as steady growth), and the change
    from frame 20 to the last (issue 6: within 10% from frame 20 to frame 200). Beside it, what
    steps it up without being a leak: the raster's colour shader builds (each kept, made at the
    first frame that needs it), Cycles' bpy datablocks."""
    from omnigen.progress import print_table
    from omnigen.rigs.render import RenderJob, Renderer

    rows, at = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        r = Renderer(RenderJob(rig="drone", frames=frames, out=Path(tmp), seed=seed, scene=scene, width=size,
                               height=size, backend=backend, quality=quality, durable=False))
        for i in range(frames):
            r.render_frame(i)
            if (i + 1) % 10 == 0:
                at[i + 1] = rss_mb()
                if backend == "cycles":
                    extra = [" ".join(f"{k} {v}" for k, v in r.backend.bs.datablock_counts().items())]
                else:
                    extra = [r.backend.rs.gl.color_builds]
                rows.append([i + 1, round(at[i + 1])] + extra)
        r.backend.close()
    head = ["frames", "resident MB", "bpy datablocks" if backend == "cycles" else "colour shader builds"]
    print_table(f"{backend}: resident MB by frame ({size}x{size}, {quality})", head, rows)
    if 20 in at and frames in at and frames > 20:
        print(f"{backend}: resident MB after frame 20 {at[20]:.0f}, after frame {frames} {at[frames]:.0f}: "
              f"{100 * (at[frames] / at[20] - 1):+.1f}% (target within 10%)")


COOP_RIGS = "ego,pole,drone"
COOP_STAGES = ("scene", "camera", "render", "annotate", "write")


def coop_renderer(out: Path, instants: int, length: int, size: int, scene: str, seed: int, fps: float = 10.0,
                  rigs: str = COOP_RIGS, start: int = 0):
    """A Renderer of instants start..start+instants-1 of a cooperative raster sequence (every rig of
    `rigs` at each instant, `length` instants a sequence) into `out`, writing as `omnigen render`
    (Renderer.run) writes: each view's files on a thread while the next is drawn."""
    from omnigen.rigs.render import RenderJob, Renderer

    r = Renderer(RenderJob(rig=rigs, frames=instants, out=out, seed=seed, scene=scene, width=size, height=size,
                           backend="raster", sequence_length=length, fps=fps, start=start, durable=False))
    r.write_behind = True
    return r


def render_instants(r, indices: range, records: list | None = None) -> dict[str, float]:
    """Render the instants `indices` from every view as Renderer.run does (render_instant) and wait
    for their files; the seconds each stage of the summary's timings took over them. The records
    made are added to `records` when given."""
    base = dict(r.summary.timings)
    for i in indices:
        made = r.render_instant(i)
        if records is not None:
            records.extend(made)
    r.flush()
    return {k: v - base[k] for k, v in r.summary.timings.items()}


def shared_share(records: list) -> tuple[float, int]:
    """The share of track-instants (a track at one instant, seen by some view) seen by two views or
    more, and how many track-instants there were: what makes the views cooperative."""
    from collections import Counter

    views = Counter()
    for rec in records:
        for track in {o.track_id for o in rec.objects if o.track_id is not None}:
            views[(rec.sequence, rec.timestamp, track)] += 1
    return (sum(n >= 2 for n in views.values()) / len(views) if views else 0.0), len(views)


def _timed(run, into: dict[str, float]) -> float:
    """Seconds `run()` took; each stage's seconds it returns are added to `into`."""
    t0 = time.perf_counter()
    stages = run()
    took = time.perf_counter() - t0
    for k, v in stages.items():
        into[k] = into.get(k, 0.0) + v
    return took


def whole_sequences(flag: str, instants: int, length: int) -> None:
    """A cooperative run renders whole sequences: `instants` a positive multiple of `length`."""
    if instants < 1 or length < 1 or instants % length:
        raise ValueError(f"{flag} {instants} must be a positive multiple of the sequence length "
                         f"(--coop-length) {length}: a run renders whole sequences")


def coop(instants: int, length: int, size: int, scene: str, seed: int, fps: float = 10.0, rounds: int = 5) -> dict:
    """Per view-frame seconds of a cooperative raster sequence (COOP_RIGS) against a single-rig
    (drone) render of the same size and as many view-frames, in one run and in alternating rounds
    (so a machine's load falls on both alike). Each renderer first renders one unit untimed that
    builds the city, the backend and its shaders (the one-off build, shown apart): the drone frame 0
    and the cooperative instant 0 of a sequence before the timed ones, which therefore build each of
    their sequence's World as a run does. The drone draws each next scene in a second process where
    `omnigen render` would (a run of 16 frames or more)."""
    whole_sequences("--coop", instants, length)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        co = coop_renderer(Path(tmp) / "coop", length + instants, length, size, scene, seed, fps)
        views = len(co.views)
        render_instants(co, range(1))
        co_build = (time.perf_counter() - t0, co.summary.timings["build"])
        frames = views * instants
        t0 = time.perf_counter()
        solo = drone_renderer(Path(tmp) / "drone", "raster", frames + 1, size, "fast", scene, seed)
        ahead = solo.draw_ahead(frames + 1)
        render_frames(solo, range(1))
        solo_build = (time.perf_counter() - t0, solo.summary.timings["build"])
        co_tm: dict[str, float] = {}
        solo_tm: dict[str, float] = {}
        co_s = solo_s = 0.0
        records: list = []
        rounds = max(1, min(rounds, instants))
        cuts = [length + instants * k // rounds for k in range(rounds + 1)]
        for a, b in zip(cuts, cuts[1:]):  # alternate: a round of instants, then as many drone frames
            co_s += _timed(lambda: render_instants(co, range(a, b), records), co_tm)
            f0 = 1 + views * (a - length)
            solo_s += _timed(lambda: render_frames(solo, range(f0, f0 + views * (b - a))), solo_tm)
        co.close()
        solo.close()
    share, tracks = shared_share(records)
    return {"instants": instants, "views": views, "view_frames": frames, "length": length, "rounds": rounds,
            "coop_s": co_s / frames, "solo_s": solo_s / frames, "ratio": co_s / solo_s,
            "stages": {k: co_tm.get(k, 0.0) / frames for k in COOP_STAGES},
            "solo_stages": {k: solo_tm.get(k, 0.0) / frames for k in COOP_STAGES},
            "coop_build": co_build, "solo_build": solo_build, "shared": share, "track_instants": tracks,
            "ahead": ahead, "size": size}


def coop_report(res: dict) -> None:
    from omnigen.progress import print_table

    rows = [["instants timed (after the warm-up instant)", res["instants"]],
            ["views per instant", res["views"]],
            ["view-frames timed, each", res["view_frames"]],
            ["sequence length, rounds alternated", f"{res['length']}, {res['rounds']}"],
            ["cooperative, s per view-frame", round(res["coop_s"], 4)],
            ["single rig (drone), s per view-frame", round(res["solo_s"], 4)],
            ["ratio cooperative / single (target <= 1.2)", round(res["ratio"], 3)],
            ["track-instants seen", res["track_instants"]],
            ["  share seen by 2+ views", f"{100 * res['shared']:.1f}%"],
            ["cooperative one-off: warm-up instant, s", round(res["coop_build"][0], 2)],
            ["  of it city + backend build, s", round(res["coop_build"][1], 2)],
            ["single-rig one-off: frame 0, s", round(res["solo_build"][0], 2)],
            ["  of it city + backend build, s", round(res["solo_build"][1], 2)],
            ["single-rig scenes drawn ahead (second process)", "yes" if res["ahead"] else "no"]]
    rows += [[f"  stage {k}, s per view-frame (coop / single)", f"{v:.4f} / {res['solo_stages'][k]:.4f}"]
             for k, v in res["stages"].items()]
    print_table(f"raster: cooperative {COOP_RIGS} against drone ({res['size']}x{res['size']})", ["measure", "value"],
                rows)


def coop_memory(instants: int, length: int, size: int, scene: str, seed: int, every: int = 100,
                fps: float = 10.0) -> None:
    """Resident memory every `every` instants of a long cooperative raster run (each instant from
    every view of COOP_RIGS), and the change from instant `every` to the last (issue 46: within
    10% over 1,000 instants), beside the raster's colour shader builds (kept, not a leak)."""
    from omnigen.progress import print_table

    whole_sequences("--memory-instants", instants, length)
    rows, at = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        r = coop_renderer(Path(tmp), instants, length, size, scene, seed, fps)
        try:
            for i in range(instants):
                r.render_instant(i)
                if (i + 1) % every == 0:
                    r.flush()
                    at[i + 1] = rss_mb()
                    rows.append([i + 1, round(at[i + 1]), r.backend.rs.gl.color_builds])
        finally:
            r.close()
    print_table(f"raster: resident MB by instant, cooperative {COOP_RIGS} ({size}x{size}, sequences of {length})",
                ["instants", "resident MB", "colour shader builds"], rows)
    if every in at and instants in at and instants > every:
        print(f"raster cooperative: resident MB after instant {every} {at[every]:.0f}, after instant {instants} "
              f"{at[instants]:.0f}: {100 * (at[instants] / at[every] - 1):+.1f}% (target within 10%)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--raster-frames", type=int, default=21)
    ap.add_argument("--cycles-frames", type=int, default=21)
    ap.add_argument("--size", type=int, default=640)
    ap.add_argument("--quality", default="fast")
    ap.add_argument("--scene", default="downtown")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-cycles", action="store_true")
    ap.add_argument("--no-raster", action="store_true")
    ap.add_argument("--memory-frames", type=int, default=0, help="also: a long run, RSS every 10 frames")
    ap.add_argument("--memory-backend", default="raster", type=backends,
                    help="raster, cycles or raster,cycles: each one's long run in turn")
    ap.add_argument("--memory-size", type=int, default=160, help="frame size of the memory run (square)")
    ap.add_argument("--memory-quality", default="preview")
    ap.add_argument("--profile", action="store_true", help="instead: where each stage's time goes, per backend and preset")
    ap.add_argument("--profile-frames", type=int, default=4, help="frames a preset of the profile renders (frame 0 untimed)")
    ap.add_argument("--profile-presets", default=",".join(PROFILE_PRESETS), help="comma-separated scene presets")
    ap.add_argument("--profile-clock", default="wall", choices=tuple(PROFILE_CLOCKS),
                    help="cpu: the rendering thread's CPU time (a loaded machine)")
    ap.add_argument("--profile-ahead", action="store_true",
                    help="draw each next scene in a second process, as a run of 16 frames or more does")
    ap.add_argument("--coop", type=int, default=0,
                    help="instead: N instants of a cooperative raster sequence (ego,pole,drone) "
                         "against as many drone view-frames")
    ap.add_argument("--coop-length", type=int, default=None,
                    help="instants a cooperative sequence (default: one sequence of --coop, "
                         "and of --memory-instants for the memory run)")
    ap.add_argument("--coop-rounds", type=int, default=5, help="rounds the cooperative and drone renders alternate in")
    ap.add_argument("--memory-instants", type=int, default=0,
                    help="with --coop: a long cooperative run, RSS by instant")
    ap.add_argument("--memory-every", type=int, default=100, help="instants between the memory run's readings")
    args = ap.parse_args()
    import os

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
          f"{args.size}x{args.size}, " + (f"scenes {args.profile_presets}" if args.profile else f"scene {args.scene}")
          + f" seed {args.seed}")
    if args.coop:
        for name in ("coop", "coop_length", "coop_rounds", "memory_instants", "memory_every"):
            if getattr(args, name) is not None and getattr(args, name) < (0 if name == "memory_instants" else 1):
                ap.error(f"--{name.replace('_', '-')} {getattr(args, name)}: must be at least 1")
        length, mem_length = args.coop_length or args.coop, args.coop_length or args.memory_instants
        try:  # both before the first render, not the memory run's after the timed one
            whole_sequences("--coop", args.coop, length)
            if args.memory_instants:
                whole_sequences("--memory-instants", args.memory_instants, mem_length)
        except ValueError as exc:
            ap.error(str(exc))
        coop_report(coop(args.coop, length, args.size, args.scene, args.seed, rounds=args.coop_rounds))
        if args.memory_instants:
            coop_memory(args.memory_instants, mem_length, args.memory_size, args.scene, args.seed, args.memory_every)
        return 0
    if args.profile:
        for backend in [b for b, off in (("raster", args.no_raster), ("cycles", args.no_cycles)) if not off]:
            profile(backend, args.profile_frames, args.size, args.quality, args.profile_presets.split(","), args.seed,
                    args.profile_clock, args.profile_ahead)
        return 0
    if not args.no_raster:
        report(bench("raster", args.raster_frames, args.size, args.quality, args.scene, args.seed))
    if not args.no_cycles:
        report(bench("cycles", args.cycles_frames, args.size, args.quality, args.scene, args.seed))
    if args.memory_frames:
        for backend in args.memory_backend:
            memory(backend, args.memory_frames, args.memory_size, args.scene, args.seed, args.memory_quality)
    return 0


if __name__ == "__main__":
    sys.exit(main())
