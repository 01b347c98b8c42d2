"""One sequence's world: the city, instant 0's agents, signal plans and motion; a Scene per instant.

Sequence q of a dataset with seed s starts from legacy frame q (randomize_frame(city, preset, s, q)):
its agents, weather and light, drawn from frame_streams(s, q). What only a sequence needs (signal
plans, motion parameters and routes) comes from sequence_streams(s, q), so a legacy frame is
never disturbed. Weather and light hold for the whole sequence; instance ids are the track ids
(an agent that leaves the city drops out of later Scenes; ids are never reused).

    world = World.build(gen.city, gen.preset, seed=7, sequence=3)
    scene = world.scene_at(k=5, fps=10.0)      # t = 0.5 s
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from omnigen.scenes.description import City, Scene, canonical
from omnigen.scenes.generate import FrameOverrides, instant_zero
from omnigen.scenes.motion import Motion, draw_motion, posed_agents
from omnigen.scenes.preset import Preset
from omnigen.scenes.seeding import sequence_streams
from omnigen.scenes.signals import SignalPlan, draw_signals


@dataclass
class World:
    """One sequence: instant 0's Scene, its signal plans and its motion (a cursor rollout)."""

    scene0: Scene
    signals: dict[str, SignalPlan]
    motion: Motion

    @classmethod
    def build(cls, city: City, preset: Preset, seed: int, sequence: int, overrides: FrameOverrides | None = None,
              user_assets=None) -> World:
        scene0, phases = instant_zero(city, preset, seed, sequence, overrides, user_assets)
        return cls.from_scene(scene0, phases)

    @classmethod
    def from_scene(cls, scene0: Scene, phases: dict[str, bool]) -> World:
        """The world of an instant 0 drawn elsewhere (a FramesAhead worker), with its queues' phases."""
        streams = sequence_streams(scene0.dataset_seed, scene0.frame_index)
        signals = draw_signals(scene0.city, phases, streams["signals"])
        return cls(scene0, signals, draw_motion(scene0.agents, scene0.city, signals, streams["motion"]))

    def scene_at(self, k: int, fps: float) -> Scene:
        """Instant k seen at `fps` frames a second: time k / fps. Instant 0 is scene0 itself."""
        t = k / float(fps)
        agents, vel = posed_agents(self.motion, self.motion.poses_at(t))
        if t == 0.0:  # scene0's agents as placed, to the byte (no agent has left yet)
            return replace(self.scene0, instant=int(k), velocities=canonical_velocities(vel))
        return replace(self.scene0, agents=tuple(canonical(a) for a in agents), instant=int(k), time=float(t),
                       velocities=canonical_velocities(vel))


def canonical_velocities(vel) -> tuple:
    """Velocities rounded as the Scene's JSON rounds them (what a record will say)."""
    return tuple(tuple(0.0 if round(c, 6) == 0 else round(c, 6) for c in v) for v in vel)
