"""Who may enter a junction when: one fixed-time signal plan per signalised junction.

A cycle gives the road along x and the road along y green in turn, each followed by amber and a
short all-red (so what entered on amber clears the box before the crossing road moves). At t = 0
the road placement gave green (placement.Placement.signals) is green, so queues placed at red
still wait and the traffic placed crossing the box still goes. Where placement drew no phase
(a preset without queues) it is drawn here, from the sequence's `signals` stream.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnigen.scenes.description import City

AMBER_S = 3.0
ALL_RED_S = 2.0
CYCLE_S = (40.0, 70.0)
STOP_BEFORE_BOX = 6.0  # metres before the junction box: behind the crosswalk and stop line

GREEN, AMBER, RED = "green", "amber", "red"


@dataclass(frozen=True)
class SignalPlan:
    """A fixed-time plan; `phase0_s` is how far into its first green the plan is at t = 0."""

    junction_id: str
    green_x: bool  # whether the road along x is the one green at t = 0
    cycle_s: float
    amber_s: float
    phase0_s: float

    def state(self, axis: str, t: float) -> str:
        """"green", "amber" or "red" for the road along `axis` ("x" or "y") at `t` seconds."""
        half = self.cycle_s / 2.0
        u = (t + self.phase0_s) % self.cycle_s
        first = (axis == "x") == self.green_x  # this road has the first half of the cycle
        if (u < half) != first:
            return RED
        into = u % half
        if into < half - self.amber_s - ALL_RED_S:
            return GREEN
        return AMBER if into < half - ALL_RED_S else RED


def draw_signals(city: City, placed: dict[str, bool], rng: np.random.Generator) -> dict[str, SignalPlan]:
    """A plan per signalised junction of `city`, keyed by its id. Every junction draws the same
    numbers whether or not placement fixed its phase, so one junction's queue never shifts
    another's plan."""
    plans = {}
    for inter in city.intersections:
        if not inter.traffic_lights:
            continue
        coin = bool(rng.random() < 0.5)
        cycle = float(rng.uniform(*CYCLE_S))
        green = cycle / 2.0 - AMBER_S - ALL_RED_S
        phase0 = float(rng.uniform(0.0, green))
        green_x = placed.get(inter.intersection_id, coin)
        plans[inter.intersection_id] = SignalPlan(inter.intersection_id, green_x, cycle, AMBER_S, phase0)
    return plans
