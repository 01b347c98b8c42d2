"""Where every random number in scenes/ comes from: explicit numpy Generators, never global state.

- The static city of (seed, preset) draws from `city_rng(seed)`.
- Frame `i` of a dataset with seed `s` draws from `frame_rng(s, i)`,
  i.e. np.random.default_rng([s, i]), so frames can be rendered in any order, on any worker.
  The frame generator is split with `Generator.spawn` into independent streams for agents,
  weather and lighting, so fixing the weather on the command line leaves the agents unchanged.

Why the city does not use default_rng(seed): numpy's SeedSequence pads entropy with zeros, so
default_rng(s) and default_rng([s, 0]) are the same stream, and the city would be correlated with
frame 0. A spawn key gives the city its own stream.
"""

from __future__ import annotations

from bisect import bisect_right
from itertools import accumulate

import numpy as np

_CITY_SPAWN_KEY = (0x0C17,)
_SEQUENCE_SPAWN_KEY = (0x5E0,)


def city_rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=_CITY_SPAWN_KEY))


def frame_rng(dataset_seed: int, frame_index: int) -> np.random.Generator:
    return np.random.default_rng([int(dataset_seed), int(frame_index)])


def frame_streams(dataset_seed: int, frame_index: int) -> dict[str, np.random.Generator]:
    """Independent child streams of frame_rng(dataset_seed, frame_index), by purpose."""
    agents, weather, lighting, extra = frame_rng(dataset_seed, frame_index).spawn(4)
    return {"agents": agents, "weather": weather, "lighting": lighting, "extra": extra}


def sequence_streams(dataset_seed: int, sequence: int) -> dict[str, np.random.Generator]:
    """What a sequence draws beyond its instant 0 (motion parameters and routes, signal plans, the
    junction its rigs meet at), by purpose.

    Why a spawn key: instant 0 of sequence q is legacy frame q, drawn from frame_rng(seed, q); a
    spawn key keeps these streams independent of it, so adding motion never moves a legacy draw.
    """
    root = np.random.SeedSequence([int(dataset_seed), int(sequence)], spawn_key=_SEQUENCE_SPAWN_KEY)
    motion, signals, meeting = (np.random.default_rng(c) for c in root.spawn(3))
    return {"motion": motion, "signals": signals, "meeting": meeting}


def instant_extra_rng(dataset_seed: int, sequence: int, instant: int) -> np.random.Generator:
    """The per-instant effects stream (rain streaks) of instant `instant` of a sequence.

    Equal to frame_streams(seed, sequence)["extra"] at instant 0: SeedSequence pads entropy with
    zeros, so [seed, q, 0] and [seed, q] seed the same stream (tested), and a one-instant sequence
    draws its effects exactly as the legacy frame q did.
    """
    return np.random.default_rng([int(dataset_seed), int(sequence), int(instant)]).spawn(4)[3]


def choice_index(rng: np.random.Generator, p) -> int:
    """`int(rng.choice(len(p), p=p))` for normalised weights, drawing the same numbers from `rng`.

    Why: Generator.choice validates its arguments on every call (~10 us); scene randomisation
    makes over a thousand such draws a frame. This is numpy's own algorithm (cumulative sum
    normalised by its last value, one `rng.random()`, the first bin above it), so frames stay
    identical to those drawn with `choice` (tested).
    """
    acc = list(accumulate(p.tolist() if isinstance(p, np.ndarray) else [float(x) for x in p]))
    last = acc[-1]
    return bisect_right([a / last for a in acc], rng.random())
