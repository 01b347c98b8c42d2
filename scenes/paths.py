"""Where an agent can go: lane centrelines and right turns through a junction, as arc-length paths.

Why paths in arc length: a vehicle's motion is then one number a step (how far along), car
following compares distances along one curve, and a pose at any instant is `pose_at(s)`:
vectorised over many s at once, so a whole fleet is posed in a few numpy calls.

A path is a chain of straight pieces and circular arcs, each tangent to the next (a turn's arc
meets both lane centrelines tangentially), so yaw is continuous along it. Past either end a path
continues straight along its end tangent (a vehicle leaving the city is dropped by the motion
model once its s passes `length`; the extension only keeps poses finite on the way).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omnigen.scenes.description import Intersection, Lane


@dataclass(frozen=True)
class Straight:
    """`length` metres from `start` along `heading` (radians about +z from +x)."""

    start: tuple[float, float]
    heading: float
    length: float

    def pose(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c, s = math.cos(self.heading), math.sin(self.heading)
        return self.start[0] + u * c, self.start[1] + u * s, np.full_like(u, self.heading)


@dataclass(frozen=True)
class Arc:
    """A circular arc round `center`; `sweep` < 0 turns clockwise (right), > 0 anticlockwise."""

    center: tuple[float, float]
    radius: float
    start_angle: float  # of the start point, seen from the centre
    sweep: float

    @property
    def length(self) -> float:
        return abs(self.sweep) * self.radius

    def pose(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        sign = 1.0 if self.sweep >= 0 else -1.0
        ang = self.start_angle + sign * u / self.radius
        x = self.center[0] + self.radius * np.cos(ang)
        y = self.center[1] + self.radius * np.sin(ang)
        return x, y, ang + sign * math.pi / 2


Segment = Straight | Arc


@dataclass(frozen=True)
class Path:
    """Tangent-continuous segments end to end; `s` runs from 0 at the first one's start."""

    segments: tuple[Segment, ...]

    @property
    def length(self) -> float:
        return float(sum(seg.length for seg in self.segments))

    def pose_at(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, yaw) at arc lengths `s` (any shape); yaw wrapped to (-pi, pi]."""
        s = np.asarray(s, dtype=np.float64)
        x, y, yaw = np.empty_like(s), np.empty_like(s), np.empty_like(s)
        lo, last = 0.0, len(self.segments) - 1
        for i, seg in enumerate(self.segments):
            hi = lo + seg.length
            # The first and last segments also take s beyond the path (straight extension).
            take = (s >= lo if i > 0 else np.ones_like(s, dtype=bool)) & (s < hi if i < last else True)
            if take.any():
                u = s[take] - lo
                if isinstance(seg, Arc) and (i == last or i == 0):
                    u = np.clip(u, 0.0, seg.length)
                x[take], y[take], yaw[take] = seg.pose(u)
            lo = hi
        return x, y, np.arctan2(np.sin(yaw), np.cos(yaw))


def lane_path(lane: Lane) -> Path:
    """A lane's centreline from its start to its end, in its driving direction."""
    return Path((Straight(tuple(lane.start), lane.heading, lane.length),))


def along(lane: Lane, xy) -> float:
    """How far along `lane` (from its start) the point `xy` lies."""
    return (xy[0] - lane.start[0]) * math.cos(lane.heading) + (xy[1] - lane.start[1]) * math.sin(lane.heading)


def turn_geometry(lane_in: Lane, lane_out: Lane, junction: Intersection) -> tuple[float, tuple[float, float], float]:
    """(crossing distance along lane_in, crossing point, radius) of a right turn.

    The radius is the smaller distance from the centrelines' crossing back to the box edge the
    vehicle enters by and on to the edge it leaves by: the largest arc tangent to both that starts
    and ends inside the box, so a turn never cuts a kerb corner or leaves the box early.
    """
    din = np.array([math.cos(lane_in.heading), math.sin(lane_in.heading)])
    dout = np.array([math.cos(lane_out.heading), math.sin(lane_out.heading)])
    # Crossing point of the two (perpendicular) centrelines.
    a0, b0 = np.asarray(lane_in.start, dtype=np.float64), np.asarray(lane_out.start, dtype=np.float64)
    t_in = float(np.dot(b0 - a0, din) - np.dot(b0 - a0, dout) * np.dot(din, dout))
    p = a0 + t_in * din
    half = np.asarray(junction.size, dtype=np.float64) / 2.0
    c = np.asarray(junction.center, dtype=np.float64)
    back = float(np.dot(p - c, din) + np.dot(np.abs(din), half))  # to the entry edge
    ahead = float(np.dot(np.abs(dout), half) - np.dot(p - c, dout))  # to the exit edge
    return t_in, (float(p[0]), float(p[1])), min(back, ahead)


def turn_path(lane_in: Lane, lane_out: Lane, junction: Intersection) -> Path:
    """Along `lane_in`, right through `junction` on the arc tangent to both centrelines, then along
    `lane_out` to its end. `lane_out` must head 90 degrees right of `lane_in`."""
    t_in, p, r = turn_geometry(lane_in, lane_out, junction)
    h_in, h_out = lane_in.heading, lane_out.heading
    din = (math.cos(h_in), math.sin(h_in))
    right = (din[1], -din[0])
    t1 = (p[0] - r * din[0], p[1] - r * din[1])
    center = (t1[0] + r * right[0], t1[1] + r * right[1])
    t2 = (p[0] + r * right[0], p[1] + r * right[1])
    out_left = along(lane_out, (lane_out.end[0], lane_out.end[1])) - along(lane_out, t2)
    return Path((Straight(tuple(lane_in.start), h_in, t_in - r),
                 Arc(center, r, math.atan2(t1[1] - center[1], t1[0] - center[0]), -math.pi / 2),
                 Straight(t2, h_out, out_left)))
