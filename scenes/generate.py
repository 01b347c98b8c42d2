"""The public entry points: a city once, then a Scene per frame.

    gen = SceneGenerator("downtown", seed=7)          # builds the static city once
    scene = gen.frame(dataset_seed=7, frame_index=3)  # agents, weather, lighting of frame 3
    scene = build_scene("arterial", seed=1)            # city of seed 1 plus its frame 0
    gen = SceneGenerator("downtown,suburban", seed=3)  # a mix: seed 3 draws suburban (3 mod 2)

Frame `i` draws only from np.random.default_rng([dataset_seed, i]) (split into independent
streams for agents, weather and lighting, see seeding.py), so frames come out the same in any
order and on any worker, and fixing the weather on the command line leaves the agents unchanged.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from omnigen.scenes.assets.build import adopt_agents, built_agents
from omnigen.scenes.description import City, Scene, canonical
from omnigen.scenes.layout import build_city
from omnigen.scenes.placement import place_world
from omnigen.scenes.preset import Preset, load_preset, preset_for_seed
from omnigen.scenes.seeding import frame_streams
from omnigen.scenes.weather import draw_lighting, draw_weather


@dataclass(frozen=True)
class FrameOverrides:
    """Values fixed by the caller (the command line) instead of drawn."""

    weather: str | None = None
    time_of_day: str | None = None
    fog_density: float | None = None
    precipitation: float | None = None


def _user_library(preset: Preset):
    if not preset.agents.user_assets:
        return []
    from omnigen.scenes.assets.user import load_library  # trimesh only when a preset asks for user assets

    folder = Path(preset.agents.user_assets)
    if not folder.is_absolute() and preset.source:
        folder = Path(preset.source).parent / folder
    return load_library(folder)


def randomize_frame(city: City, preset: Preset, dataset_seed: int, frame_index: int,
                    overrides: FrameOverrides | None = None, user_assets=None) -> Scene:
    """Agents, weather and lighting of one frame over a fixed city."""
    return instant_zero(city, preset, dataset_seed, frame_index, overrides, user_assets)[0]


def instant_zero(city: City, preset: Preset, dataset_seed: int, frame_index: int,
                 overrides: FrameOverrides | None = None, user_assets=None) -> tuple[Scene, dict[str, bool]]:
    """randomize_frame's Scene and the signal phases its queues were placed by (placement.place_world),
    which the Scene does not carry: a sequence (scenes/world.py) starts from frame `frame_index`'s
    world and keeps its lights as its queues assumed them."""
    o = overrides or FrameOverrides()
    streams = frame_streams(dataset_seed, frame_index)
    weather = draw_weather(streams["weather"], preset.weather.kinds, o.weather, o.fog_density, o.precipitation)
    lighting = draw_lighting(streams["lighting"], preset.lighting.times, preset.lighting.latitude, weather, o.time_of_day)
    if user_assets is None:
        user_assets = _user_library(preset)
    placed = place_world(city, preset.agents, streams["agents"], user_assets)
    agents = tuple(canonical(a) for a in placed.agents)
    # The city is already canonical (build_city returns it so) and shared by every frame.
    scene = Scene(city, agents, canonical(weather), canonical(lighting), int(dataset_seed), int(frame_index))
    return scene, placed.signals


class SceneGenerator:
    """Holds a preset and its city; draws frames. Build once per process, call frame() often."""

    def __init__(self, preset: str | Path | Preset = "downtown", seed: int = 0) -> None:
        """`preset`: a Preset, a name or TOML path, or a mix "a,b,c" of which the seed draws one
        (`preset.preset_for_seed`); `self.preset.name` says which."""
        self.preset = preset if isinstance(preset, Preset) else load_preset(preset_for_seed(preset, seed))
        self.seed = int(seed)
        self.city = build_city(self.preset, self.seed)
        self.user_assets = _user_library(self.preset)

    def frame(self, dataset_seed: int | None = None, frame_index: int = 0, overrides: FrameOverrides | None = None) -> Scene:
        ds = self.seed if dataset_seed is None else dataset_seed
        return randomize_frame(self.city, self.preset, ds, frame_index, overrides, self.user_assets)


def build_scene(preset: str | Path | Preset = "downtown", seed: int = 0, overrides: FrameOverrides | None = None) -> Scene:
    """The city of (preset, seed) with its frame 0 drawn from the same seed."""
    return SceneGenerator(preset, seed).frame(seed, 0, overrides)


_WORKER_GEN: list[SceneGenerator] = []  # in a FramesAhead worker: the generator it draws with


_WORKER_THEN: list[Callable[[Scene], Any] | None] = [None]  # and what it draws after each frame


def _start_worker(gen: SceneGenerator, then: Callable[[Scene], Any] | None = None) -> None:
    _WORKER_GEN[:] = [gen]
    _WORKER_THEN[:] = [then]


def _worker_frame(dataset_seed: int, frame_index: int, overrides: FrameOverrides | None, meshes: bool = False) -> tuple:
    """A frame drawn in the worker, less the city (the caller has its own; it is the large part),
    with `meshes` its agents' meshes (assets.build.built_agents), else None, and what the caller's
    `then` makes of it (None without one)."""
    scene = _WORKER_GEN[0].frame(dataset_seed, frame_index, overrides)
    then = _WORKER_THEN[0]
    return (scene.agents, scene.weather, scene.lighting, built_agents(scene.agents) if meshes else None,
            then(scene) if then is not None else None)


class FramesAhead:
    """A SceneGenerator's frames drawn ahead, in a second process, while this one renders.

    Why: drawing a frame (agents, weather, light) is single-threaded Python, 0.1-0.2 s a downtown
    frame, that the renderer otherwise waits for. A frame depends only on (city, seed, index), so
    a worker holding a copy of the city draws the very Scene this process would
    (tests/rigs/test_render_reuse.py); it comes back without the city and is joined to this
    process's. The worker is forked here, at once: it inherits the built city (a spawned one would
    build it again and re-run the caller's main script), and a renderer makes this before its GL
    context and writer thread exist (Renderer.run). If it dies, frames are drawn here again.

    meshes: the worker also builds every agent's mesh (assets.build.built_agents) and this process
    adopts them into its mesh cache, for a backend that builds every agent of a frame (Cycles'
    Blender scene: ~0.45 s a downtown frame, more than drawing the frame). Not for the raster,
    which builds only the agents in view, fewer than the worker would.

    then: what else depends on the frame alone and is worth drawing ahead, a function of its Scene
    run in the worker after it (the renderer's first camera draw: rigs/render.py first_camera);
    frame_with hands back its result, picklable, as this process would have made it.
    """

    def __init__(self, gen: SceneGenerator, meshes: bool = False, then: Callable[[Scene], Any] | None = None) -> None:
        self.gen, self.meshes = gen, meshes
        self._pool: ProcessPoolExecutor | None = ProcessPoolExecutor(
            1, mp_context=multiprocessing.get_context("fork"), initializer=_start_worker, initargs=(gen, then))
        self._pool.submit(int)  # forks now (a fork pool starts its worker at the first task)
        self._asked: dict[tuple, Future] = {}

    def ask(self, dataset_seed: int, frame_index: int, overrides: FrameOverrides | None = None) -> None:
        """Start drawing a frame that `frame` will be asked for."""
        if self._pool is not None:
            try:
                self._asked[(dataset_seed, frame_index, overrides)] = self._pool.submit(
                    _worker_frame, dataset_seed, frame_index, overrides, self.meshes)
            except BrokenProcessPool:
                self.close()

    def frame(self, dataset_seed: int, frame_index: int, overrides: FrameOverrides | None = None) -> Scene:
        """SceneGenerator.frame: the worker's drawing if it was asked for (waiting for it), else drawn here."""
        return self.frame_with(dataset_seed, frame_index, overrides)[0]

    def frame_with(self, dataset_seed: int, frame_index: int, overrides: FrameOverrides | None = None
                   ) -> tuple[Scene, Any]:
        """frame's Scene and what `then` made of it in the worker; None for the latter where the
        frame was drawn here (not asked for, or the worker died): the caller makes it itself."""
        asked = self._asked.pop((dataset_seed, frame_index, overrides), None)
        if asked is not None:
            try:
                agents, weather, lighting, built, after = asked.result()
                if built is not None:
                    adopt_agents(built, agents)
                return Scene(self.gen.city, agents, weather, lighting, int(dataset_seed), int(frame_index)), after
            except BrokenProcessPool:
                self.close()
        return self.gen.frame(dataset_seed, frame_index, overrides), None

    def close(self) -> None:
        pool, self._pool = self._pool, None
        self._asked.clear()
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
