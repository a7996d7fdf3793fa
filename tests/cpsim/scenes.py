"""Tiny hand-made scenarios for simulator tests.

The default road: a straight two-lane road along +x from x = -50 to x = 250 m. Lane
centrelines at y = 0 and y = 3.7 (both heading +x), painted line at y = 1.85, road edges
at y = -1.85 and y = 5.55.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from cpsim.scenario.datatypes import NUM_STEPS, AgentType, RoadType, Scenario

LANE_WIDTH = 3.7
ROAD_X = (-50.0, 250.0)
EDGE_LOW = -LANE_WIDTH / 2
EDGE_HIGH = LANE_WIDTH * 1.5


def straight_road(x0: float = ROAD_X[0], x1: float = ROAD_X[1], spacing: float = 5.0):
    """Polylines of the default road: (points (P, 2), offsets (R+1,), types (R,))."""
    xs = np.arange(x0, x1 + 1e-6, spacing)
    lines = [
        (np.stack([xs, np.zeros_like(xs)], 1), RoadType.LANE),
        (np.stack([xs, np.full_like(xs, LANE_WIDTH)], 1), RoadType.LANE),
        (np.stack([xs, np.full_like(xs, LANE_WIDTH / 2)], 1), RoadType.ROAD_LINE),
        (np.stack([xs, np.full_like(xs, EDGE_LOW)], 1), RoadType.ROAD_EDGE),
        (np.stack([xs, np.full_like(xs, EDGE_HIGH)], 1), RoadType.ROAD_EDGE),
    ]
    return polylines(lines)


def polylines(lines: Sequence[tuple[np.ndarray, int]]):
    pts = np.concatenate([p for p, _ in lines]).astype(np.float32)
    offsets = np.concatenate([[0], np.cumsum([len(p) for p, _ in lines])]).astype(np.int32)
    types = np.array([t for _, t in lines], np.int8)
    return pts, offsets, types


def agent(x: float, y: float, heading: float = 0.0, speed: float = 0.0, length: float = 4.5,
          width: float = 2.0, kind: int = AgentType.VEHICLE, goal: tuple[float, float] | None = None,
          valid_steps: int = NUM_STEPS, accel: float = 0.0, yaw_rate: float = 0.0) -> dict:
    """Agent spec whose log moves with constant acceleration and yaw rate from (x, y)."""
    return dict(x=x, y=y, heading=heading, speed=speed, length=length, width=width, kind=kind,
                goal=goal, valid_steps=valid_steps, accel=accel, yaw_rate=yaw_rate)


def make_scenario(agents: Sequence[dict], roads=None, ego: int = 0, sid: str = "test") -> Scenario:
    """Scenario with the given agent specs (see :func:`agent`) on ``roads`` (default road)."""
    n, T, dt = len(agents), NUM_STEPS, 0.1
    xy = np.zeros((n, T, 2), np.float32)
    hd = np.zeros((n, T), np.float32)
    vel = np.zeros((n, T, 2), np.float32)
    valid = np.zeros((n, T), bool)
    goals = np.zeros((n, 2), np.float32)
    sizes = np.zeros((n, 2), np.float32)
    types = np.zeros(n, np.int8)
    for i, a in enumerate(agents):
        x, y, h, v = a["x"], a["y"], a["heading"], a["speed"]
        for t in range(T):
            xy[i, t] = (x, y)
            hd[i, t] = h
            vel[i, t] = (v * np.cos(h), v * np.sin(h))
            x += v * np.cos(h) * dt
            y += v * np.sin(h) * dt
            h += a["yaw_rate"] * dt
            v = max(v + a["accel"] * dt, 0.0)
        valid[i, :a["valid_steps"]] = True
        last = a["valid_steps"] - 1
        goals[i] = a["goal"] if a["goal"] is not None else xy[i, last]
        sizes[i] = (a["length"], a["width"])
        types[i] = a["kind"]
    pts, offs, rtypes = roads if roads is not None else straight_road()
    return Scenario(id=sid, log_xy=xy, log_heading=hd, log_velocity=vel, log_valid=valid,
                    goal_xy=goals, sizes=sizes, agent_types=types, road_points=pts, road_offsets=offs,
                    road_types=rtypes, ego_index=ego, family="test", source=f"test:{sid}")


def two_cars(gap: float = 20.0, speed: float = 10.0) -> Scenario:
    """Ego at the origin in the right lane driving +x, a second car ``gap`` m ahead in the
    same lane at the same speed (both controllable: goals 80 m ahead)."""
    return make_scenario([
        agent(0.0, 0.0, speed=speed, goal=(80.0, 0.0)),
        agent(gap, 0.0, speed=speed, goal=(gap + 80.0, 0.0)),
    ], sid=f"two_cars_{gap}")


def small_pool(n: int = 3) -> list[Scenario]:
    """A few different small scenarios (for snapshot / pool tests)."""
    out = [two_cars(20.0 + 5 * i, 8.0 + i) for i in range(n)]
    return out
