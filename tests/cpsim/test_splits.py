"""Interactivity score and the Interactive-N / Random-N splits (cpsim.scenario.splits)."""

from __future__ import annotations

import dataclasses
import gzip
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import cpsim.scenario as cs
from cpsim.scenario import AgentType, RoadType, Scenario
from cpsim.scenario.splits import (
    interactive_split,
    interactivity_report,
    interactivity_score,
    interactivity_terms,
    random_split,
    track_tasks,
)

T = 91
DT = 0.1
LENGTH_2 = 5.0  # box length of the steering agent
YAW_STEP = 0.02  # rad per step of the steering agent while it turns


def hand_scenario(ego_goal_m: float = 30.0, sid: str = "hand") -> Scenario:
    """Six agents with closed-form interactivity terms (see test_score_matches_hand_computation).

    0 ego vehicle: x = t m, 10 m/s straight, valid throughout.
    1 vehicle: speed 5 + 0.01 t^2 (jerk exactly 2 m/s^3), 5 m ahead of the ego for t < 30.
    2 vehicle: 10 m/s, heading turns 0.02 rad/step until t = 45, then straight; 50 m away.
    3 pedestrian: erratic speed and heading (excluded from the kinematic terms), 3 m beside the ego.
    4 cyclist: 0.5 m/s (too slow for steering), heading noise, 10.5 m beside the ego (never near).
    5 vehicle: valid only from t = 50 (-10000 before), 8 m behind the ego.
    """
    rng = np.random.default_rng(0)
    n = 6
    t = np.arange(T, dtype=np.float64)
    ego_xy = np.stack([t * 1.0, np.zeros(T)], axis=-1)
    xy = np.zeros((n, T, 2))
    xy[0] = ego_xy
    xy[1] = ego_xy + np.where(t[:, None] < 30, [5.0, 0.0], [100.0, 0.0])
    xy[2] = ego_xy + [0.0, 50.0]
    xy[3] = ego_xy + [0.0, 3.0]
    xy[4] = ego_xy + [0.0, 10.5]
    xy[5] = ego_xy + [-8.0, 0.0]
    speed = np.zeros((n, T))
    speed[0] = 10.0
    speed[1] = 5.0 + 0.01 * t**2
    speed[2] = 10.0
    speed[3] = rng.uniform(0.0, 3.0, T)
    speed[4] = 0.5
    speed[5] = 10.0
    heading = np.zeros((n, T))
    heading[2] = YAW_STEP * np.minimum(t, 45)
    heading[3] = rng.uniform(-3.0, 3.0, T)
    heading[4] = rng.uniform(-0.5, 0.5, T)
    velocity = np.stack([speed * np.cos(heading), speed * np.sin(heading)], axis=-1)
    valid = np.ones((n, T), bool)
    valid[5, :50] = False
    for arr in (xy, velocity):
        arr[5, :50] = -10000.0
    heading[5, :50] = -10000.0
    goal = xy[:, 0] + np.array([[ego_goal_m, 0], [12, 0], [5, 0], [0, 20], [3, 0], [40, 0]], np.float64)
    sizes = np.tile([4.5, 2.0], (n, 1))
    sizes[2, 0] = LENGTH_2
    return Scenario(
        id=sid,
        log_xy=xy.astype(np.float32),
        log_heading=heading.astype(np.float32),
        log_velocity=velocity.astype(np.float32),
        log_valid=valid,
        goal_xy=goal.astype(np.float32),
        sizes=sizes.astype(np.float32),
        agent_types=np.array([0, 0, 0, AgentType.PEDESTRIAN, AgentType.CYCLIST, 0], np.int8),
        road_points=np.array([[0, -5], [100, -5]], np.float32),
        road_offsets=np.array([0, 2], np.int32),
        road_types=np.array([RoadType.ROAD_EDGE], np.int8),
        ego_index=0,
        family="test",
    )


# ----------------------------------------------------------------------------- hand-made scenes, one per term
def scene(xy, *, velocity=None, heading=None, valid=None, goal=None, types=None, lengths=None,
          lanes=(), ego: int = 0, sid: str = "term") -> Scenario:
    """A scenario from (N, T, 2) positions. Defaults: velocity = forward difference of the
    positions / dt (last step repeated), heading = direction of motion (0 when still), every
    step valid, goal = last position, vehicles of 4.5 x 2 m, and ``lanes`` as the lane
    centrelines (a far road edge when none)."""
    xy = np.asarray(xy, np.float64)
    n = xy.shape[0]
    if velocity is None:
        velocity = np.diff(xy, axis=1, append=xy[:, -1:] * 2 - xy[:, -2:-1]) / DT
    velocity = np.asarray(velocity, np.float64)
    if heading is None:
        heading = np.arctan2(velocity[..., 1], velocity[..., 0])
    valid = np.ones(xy.shape[:2], bool) if valid is None else np.asarray(valid, bool)
    goal = xy[:, -1] if goal is None else np.asarray(goal, np.float64)
    types = np.zeros(n, np.int8) if types is None else np.asarray(types, np.int8)
    sizes = np.tile([4.5, 2.0], (n, 1))
    if lengths is not None:
        sizes[:, 0] = lengths
    polylines = [np.asarray(p, np.float32) for p in lanes] or [np.array([[-5000, -5000], [-4990, -5000]], np.float32)]
    return Scenario(
        id=sid,
        log_xy=xy.astype(np.float32),
        log_heading=np.asarray(heading, np.float32),
        log_velocity=velocity.astype(np.float32),
        log_valid=valid,
        goal_xy=goal.astype(np.float32),
        sizes=sizes.astype(np.float32),
        agent_types=types,
        road_points=np.concatenate(polylines),
        road_offsets=np.concatenate([[0], np.cumsum([len(p) for p in polylines])]).astype(np.int32),
        road_types=np.full(len(polylines), RoadType.LANE if lanes else RoadType.ROAD_EDGE, np.int8),
        ego_index=ego,
        family="test",
    )


TT = np.arange(T, dtype=np.float64)


def still(x: float, y: float) -> np.ndarray:
    """(T, 2) an agent parked at (x, y)."""
    return np.tile([x, y], (T, 1)).astype(np.float64)


def ego_along_x() -> np.ndarray:
    """(T, 2) the ego driving +x at 10 m/s from the origin (x = t m)."""
    return np.stack([TT, np.zeros(T)], axis=-1)


def test_agents_within_50m_at_t0() -> None:
    xy = np.stack([still(0, 0), still(10, 0), still(0, 49.9), still(30, 40),  # 50 m exactly: counts
                   still(30, 40.2), still(3, 0), still(-60, 0)])
    valid = np.ones((7, T), bool)
    valid[5, 0] = False  # 3 m away but not valid at t0
    t = interactivity_terms(scene(xy, valid=valid, goal=np.tile([100.0, 0], (7, 1))))
    assert t.agents_near_t0 == 3 and t.agents_valid_t0 == 6
    assert t.capped()["agents_near_t0"] == pytest.approx(3 / 15)
    many = np.stack([still(0, 0)] + [still(2.0 * k, 5) for k in range(20)])
    assert interactivity_terms(scene(many)).capped()["agents_near_t0"] == 1.0  # 20 agents, capped at 15


def test_mean_summed_accel_change() -> None:
    n = 5
    xy = np.stack([still(0, 0), still(0, 20), still(0, 40), still(0, 60), still(0, 80)])
    speed = np.full((n, T), 10.0)
    speed[1] = 10.0 + 0.1 * (TT % 2)  # a = +-1 m/s^2: |d a| = 2 every step
    speed[2] = 10.0 + 1.0 * (TT % 2)  # a = +-10, clipped to +-4: |d a| = 8 every step
    speed[3] = 10.0 + 0.1 * (TT % 2)  # |d a| = 2, but valid only from t = 50
    speed[4] = 10.0 + 1.0 * (TT % 2)  # a pedestrian: not a wheeled agent, left out
    velocity = np.stack([speed, np.zeros((n, T))], axis=-1)
    valid = np.ones((n, T), bool)
    valid[3, :50] = False
    s = scene(xy, velocity=velocity, heading=np.zeros((n, T)), valid=valid,
              types=[0, 0, AgentType.CYCLIST, 0, AgentType.PEDESTRIAN])
    # 89 step triples t..t+2; agent 3 has them for t = 50..88 (39): summed per step, mean over steps.
    expected = (89 * (2 + 8) + 39 * 2) / 89
    t = interactivity_terms(s)
    assert t.mean_accel_change == pytest.approx(expected, rel=1e-4)
    assert t.capped()["mean_accel_change"] == pytest.approx(expected / 30, rel=1e-4)
    # summed over agents: four copies of agent 2 saturate the cap (4 x 8 = 32 > 30)
    crowd = scene(np.stack([still(0, 0)] + [still(0, 20 * k) for k in range(1, 5)]),
                  velocity=np.stack([np.stack([np.full(T, 10.0)] + [speed[2]] * 4), np.zeros((5, T))], -1),
                  heading=np.zeros((5, T)))
    assert interactivity_terms(crowd).mean_accel_change == pytest.approx(32.0, rel=1e-4)
    assert interactivity_terms(crowd).capped()["mean_accel_change"] == 1.0


def test_mean_steering_change() -> None:
    n = 4
    xy = np.stack([still(0, 0), still(0, 20), still(0, 40), still(0, 60)])
    heading = np.zeros((n, T))
    heading[1] = 0.02 * np.minimum(TT, 45)  # 0.2 rad/s until t = 45, then straight
    heading[2, 60:] = 0.5  # one 5 rad/s step: atan(4 x 5 / 10) = 1.107, clipped to 1 rad
    heading[3] = np.where(TT % 2 == 0, 0.0, 1.0)  # erratic, but at 0.5 m/s: no steering
    speed = np.array([10.0, 10.0, 10.0, 0.5])[:, None] * np.ones((n, T))
    velocity = np.stack([speed * np.cos(heading), speed * np.sin(heading)], axis=-1)
    s = scene(xy, velocity=velocity, heading=heading, lengths=[4.0, 4.0, 4.0, 4.0])
    # delta_t = atan(length x yaw rate / speed): agent 1 from atan(0.08) to 0 once (t = 44 -> 45);
    # agent 2 from 0 to 1 and back (t = 58 -> 59 -> 60). Samples: 89 for each of agents 0-2.
    expected = (math.atan(4.0 * 0.2 / 10.0) + 2 * 1.0) / (3 * 89)
    t = interactivity_terms(s)
    assert t.mean_steer_change == pytest.approx(expected, rel=1e-4)
    assert t.capped()["mean_steer_change"] == pytest.approx(expected / 2, rel=1e-4)
    # driving straight along +-pi is no steering (headings wrap)
    wrap_heading = heading.copy()
    wrap_heading[0] = np.where(TT % 2 == 0, np.pi - 1e-4, -np.pi + 1e-4)
    wrapped = dataclasses.replace(s, log_heading=wrap_heading.astype(np.float32))
    assert interactivity_terms(wrapped).mean_steer_change == pytest.approx(
        expected + 88 * 2 * math.atan(4.0 * 2e-3 / 10.0) / (3 * 89), rel=1e-3)


def test_mean_agents_within_10m() -> None:
    ego = ego_along_x()
    xy = np.stack([ego, ego + [0, 10], ego + [0, 10.5], ego + [6, 8], still(45, 0)])
    valid = np.ones((5, T), bool)
    valid[3, 60:] = False
    s = scene(xy, valid=valid, types=[0, AgentType.PEDESTRIAN, 0, AgentType.CYCLIST, 0])
    # agent 1 (10 m, any type) for 91 steps, agent 3 (10 m) for its 60 valid steps, the
    # parked car at x = 45 while the ego is within 10 m of it (t = 35..55, 21 steps).
    t = interactivity_terms(s)
    assert t.mean_neighbours == pytest.approx((91 + 60 + 21) / 91)
    assert t.capped()["mean_neighbours"] == pytest.approx((91 + 60 + 21) / 91 / 3)


@pytest.mark.parametrize("goal_m, capped", [(10.0, 0.0), (30.0, 0.5), (50.0, 1.0), (200.0, 1.0)])
def test_ego_goal_distance_term(goal_m: float, capped: float) -> None:
    xy = np.stack([still(0, 0)] + [still(0, 20 * k) for k in range(1, 5)])
    goal = np.tile([0.0, 0.0], (5, 1))
    goal[0] = [0.6 * goal_m, 0.8 * goal_m]
    t = interactivity_terms(scene(xy, goal=goal))
    assert t.ego_goal_distance == pytest.approx(goal_m, rel=1e-6)
    assert t.capped()["ego_goal_distance"] == pytest.approx(capped, abs=1e-6)


def test_path_crossings_within_5m() -> None:
    ego = ego_along_x()  # x = 0..90 on y = 0
    crossing_early = np.stack([np.full(T, 50.0), 45.0 - TT], axis=-1)  # crosses x = 50 at t = 45 (ego at 45)
    crossing_late = np.stack([np.full(T, 20.0), 80.0 - TT], axis=-1)  # crosses x = 20 at t = 80, ego long gone
    xy = np.stack([ego, crossing_early, crossing_late,
                   ego + [0, 5.0],  # alongside at 5 m: counts
                   ego + [0, 5.1],  # 5.1 m: does not
                   still(95, 4),  # parked 5 m from where the ego stops (90, 0)? 6.4 m: no
                   still(93, 4),  # 5 m from (90, 0): counts
                   np.stack([np.full(T, 60.0), 30.0 - TT], axis=-1)])  # crosses only while invalid
    valid = np.ones((8, T), bool)
    valid[7, 20:40] = False  # y = 10..-9 at x = 60: the crossing is not in its valid log
    valid[7, 40:] = False
    s = scene(xy, valid=valid, types=[0, AgentType.PEDESTRIAN, 0, 0, 0, 0, 0, 0])
    t = interactivity_terms(s)
    assert t.path_crossings == 4  # agents 1, 2, 3, 6
    assert t.capped()["path_crossings"] == pytest.approx(4 / 5)


def test_time_to_collision_steps() -> None:
    ego = ego_along_x()  # 10 m/s along +x
    xy = np.stack([
        ego,
        still(100, 0),  # closing at 10 m/s; TTC < 3 s once closer than 30 m: t = 71..90 (20 steps)
        ego + [20.0, 0.0] + np.stack([0.1 * TT, np.zeros(T)], -1),  # ahead, receding: never
        still(75, 1.0),  # closing; TTC < 3 s for t in 46..75 (overlaps agent 1's steps)
        ego + [25.0, 0.0] - np.stack([0.004 * TT, np.zeros(T)], -1),  # closing at 0.04 m/s: never
        ego + [60.0, 0.0] - np.stack([2.0 * TT, np.zeros(T)], -1),  # closing at 20 m/s, valid only > 50 m
    ])
    valid = np.ones((6, T), bool)
    valid[5, 4:] = False  # distances 60, 58, 56, 54 m: TTC < 3 s but beyond 50 m
    s = scene(xy, valid=valid)
    d3 = np.hypot(75.0 - TT, 1.0)
    closing3 = 10.0 * (75.0 - TT) / d3
    steps3 = set(np.flatnonzero((closing3 > 0.1) & (d3 < 3 * closing3)).tolist())
    expected = set(range(71, 91)) | steps3
    t = interactivity_terms(s)
    assert steps3 and min(steps3) == 46 and t.ttc_steps == len(expected)
    assert t.capped()["ttc_steps"] == 1.0  # more than 20 steps
    only_far = interactivity_terms(scene(xy[[0, 1, 2, 4, 5]], valid=valid[[0, 1, 2, 4, 5]]))
    assert only_far.ttc_steps == 20 and only_far.capped()["ttc_steps"] == 1.0
    assert interactivity_terms(scene(xy[[0, 2, 4, 5]], valid=valid[[0, 2, 4, 5]])).ttc_steps == 0


def test_ego_heading_change() -> None:
    xy = np.stack([still(0, 0)] + [still(0, 20 * k) for k in range(1, 5)])
    heading = np.zeros((5, T))
    heading[0] = np.linspace(0.2, 1.2, T)  # net change 1 rad
    t = interactivity_terms(scene(xy, heading=heading))
    assert t.ego_heading_change == pytest.approx(1.0, rel=1e-5)
    assert t.capped()["ego_heading_change"] == pytest.approx(1.0 / (math.pi / 2), rel=1e-5)
    heading[0] = np.where(TT < 45, 3.0, -3.0)  # across +-pi: 0.28 rad, not 6
    valid = np.ones((5, T), bool)
    valid[0, 80:] = False  # the last valid step counts
    heading[0, 80:] = 1.0
    t = interactivity_terms(scene(xy, heading=heading, valid=valid))
    assert t.ego_heading_change == pytest.approx(2 * math.pi - 6.0, rel=1e-4)
    heading[0] = np.linspace(0.0, -3.0, T)  # a U-turn saturates
    assert interactivity_terms(scene(xy, heading=heading)).capped()["ego_heading_change"] == 1.0


# Lanes: a straight lane to x = 100, its straight continuation to x = 500, and a left turn
# that starts where the first one ends; an opposite lane 3.5 m to the left.
STRAIGHT_1 = [[-20.0 + k, 0.0] for k in range(121)]
STRAIGHT_2 = [[100.0 + 2 * k, 0.0] for k in range(201)]
LEFT_TURN = [[100.0 + 30 * math.sin(a), 30 - 30 * math.cos(a)] for a in np.linspace(0, math.pi / 2, 20)] + \
    [[130.0, 30.0 + 2 * k] for k in range(1, 100)]
OPPOSITE = [[300.0 - 2 * k, 3.5] for k in range(161)]
LANES = (STRAIGHT_1, LEFT_TURN, STRAIGHT_2, OPPOSITE)


def lane_scene(goal_xy, lanes=LANES, ego_heading: float = 0.0, ego_y: float = 0.0) -> Scenario:
    ego = np.tile([0.0, ego_y], (T, 1))  # parked at the start: only the lane chain matters here
    xy = np.stack([ego] + [still(-30.0 * k, 40) for k in range(1, 5)])
    heading = np.zeros((5, T))
    heading[0] = ego_heading
    goal = np.tile([0.0, 0.0], (5, 1))
    goal[0] = goal_xy
    return scene(xy, heading=heading, goal=goal, lanes=lanes)


@pytest.mark.parametrize("goal, on_chain", [
    ((60.0, 2.0), True),  # on the ego's lane
    ((250.0, -4.9), True),  # on its straight continuation, within 5 m
    ((250.0, 5.5), False),  # 5.5 m off
    ((298.0, 0.0), True),  # within the 300 m ahead
    ((306.0, 0.0), False),  # beyond 300 m + 5 m
    ((130.0, 100.0), False),  # on the left turn: not the straight chain
    ((-15.0, 0.0), False),  # on the lane, but behind the ego
])
def test_lane_multiplier(goal, on_chain: bool) -> None:
    t = interactivity_terms(lane_scene(goal))
    assert t.goal_on_lane_chain is on_chain
    assert t.lane_mult == (0.5 if on_chain else 1.0)
    chain = cs.splits.ego_lane_chain(lane_scene(goal))
    assert chain[0] == pytest.approx([0.0, 0.0]) and chain[-1] == pytest.approx([300.0, 0.0], abs=1e-4)


def test_lane_chain_picks_the_ego_lane_and_follows_continuations() -> None:
    # Facing -x, the ego's lane is the opposite one (3.5 m away), not the nearer straight lane.
    chain = cs.splits.ego_lane_chain(lane_scene((50.0, 0.0), ego_heading=math.pi, ego_y=0.5))
    assert np.allclose(chain[:, 1], 3.5) and chain[-1][0] == pytest.approx(-20.0, abs=1e-3)  # lane ends at x = -20
    assert interactivity_terms(lane_scene((-10.0, 3.0), ego_heading=math.pi, ego_y=0.5)).lane_mult == 0.5
    # No lane within 5 m, or none aligned with the ego: no chain, the goal is off it.
    assert cs.splits.ego_lane_chain(lane_scene((60.0, 0.0), ego_y=-6.0)) is None
    assert interactivity_terms(lane_scene((60.0, 0.0), ego_y=-6.0)).lane_mult == 1.0
    assert cs.splits.ego_lane_chain(lane_scene((60.0, 0.0), ego_heading=math.pi / 2)) is None
    # Without the straight continuation the chain turns left with the only successor.
    turn = lane_scene((130.0, 100.0), lanes=(STRAIGHT_1, LEFT_TURN))
    assert interactivity_terms(turn).lane_mult == 0.5


def test_lane_multiplier_halves_the_score() -> None:
    on = lane_scene((250.0, 0.0))
    off = lane_scene((250.0, 0.0), lanes=(STRAIGHT_1, LEFT_TURN, OPPOSITE))  # the chain turns away
    t_on, t_off = interactivity_terms(on), interactivity_terms(off)
    assert (t_on.lane_mult, t_off.lane_mult) == (0.5, 1.0)
    assert t_on.score == pytest.approx(0.5 * t_off.score) and t_off.score > 0


def test_score_is_the_weighted_sum_of_capped_terms() -> None:
    """One scene with every term known in closed form (weights and caps of BehaviorBench)."""
    ego = ego_along_x()
    xy = np.stack([ego, still(100, 0), ego + [0, 5.0], still(30, 40), still(200, 0), still(0, 8)])
    heading = np.zeros((6, T))
    heading[0] = np.linspace(0.0, 0.5, T)  # net heading change 0.5 rad (motion stays +x)
    velocity = np.stack([np.full((6, T), 0.0), np.zeros((6, T))], axis=-1)
    velocity[0, :, 0] = velocity[2, :, 0] = 10.0
    goal = np.tile([0.0, 0.0], (6, 1))
    goal[0] = [0.0, 30.0]  # 30 m from the ego's start, off its lane
    s = scene(xy, heading=heading, velocity=velocity, goal=goal, lanes=(STRAIGHT_1, STRAIGHT_2))
    t = interactivity_terms(s)
    # agents within 50 m at t0: 2 (5 m), 3 (50 m), 5 (8 m); the parked car at x = 100 is 100 m away
    assert t.agents_near_t0 == 3
    assert t.mean_accel_change == 0.0  # constant speeds
    # the ego's heading turns 0.5 / 90 rad per step at 10 m/s: steering atan(4.5 x 0.0556 / 10)
    # constant, so no steering change (agent 2 moves straight)
    assert t.mean_steer_change == pytest.approx(0.0, abs=1e-5)
    # within 10 m: agent 2 always; agent 5 (x = 0, y = 8) while |t| <= 6 (7 steps);
    # the parked car at 100 m is within 10 m for no step (the ego stops at x = 90)... 10 m: t = 90
    near_100 = int(np.sum(np.abs(100.0 - TT) <= 10.0))
    mean_neighbours = (91 + 7 + near_100) / 91
    assert t.mean_neighbours == pytest.approx(mean_neighbours)
    # paths within 5 m: agent 2 (alongside), agent 1 (parked at x = 100: 10 m from the last ego
    # point, no); agent 5 (8 m from the ego's path), no
    assert t.path_crossings == 1
    # TTC: only the parked car at x = 100 ahead: t = 71..90
    assert t.ttc_steps == 20
    assert t.ego_heading_change == pytest.approx(0.5, rel=1e-5)
    assert not t.goal_on_lane_chain and t.lane_mult == 1.0
    expected = (0.10 * 3 / 15 + 0.10 * 0 + 0.05 * 0 + 0.10 * min(mean_neighbours / 3, 1)
                + 0.15 * (30 - 10) / 40 + 0.25 * 1 / 5 + 0.20 * 1.0 + 0.05 * 0.5 / (math.pi / 2))
    assert t.score == pytest.approx(expected, rel=1e-4)
    assert sum(t.contributions().values()) == pytest.approx(t.score)
    assert interactivity_score(s) == t.score and cs.interactivity_score is interactivity_score
    assert sum(w for _n, w, _c in cs.splits.TERMS) == pytest.approx(1.0)
    assert [(w, c) for _n, w, c in cs.splits.TERMS] == [(0.10, 15.0), (0.10, 30.0), (0.05, 2.0), (0.10, 3.0),
                                                         (0.15, 40.0), (0.25, 5.0), (0.20, 20.0),
                                                         (0.05, math.pi / 2)]


def test_hand_scenario_terms() -> None:
    """The six-agent scene of the split tests: the terms its construction fixes."""
    t = interactivity_terms(hand_scenario())
    assert t.eligible and t.reason == "" and t.agents_valid_t0 == 5
    assert t.agents_near_t0 == 4  # agents 1 (5 m), 2 (50 m), 3 (3 m), 4 (10.5 m); 5 not valid at t0
    # Neighbours within 10 m of the ego: agent 1 for 30 steps, the pedestrian for 91,
    # agent 5 for 41; the cyclist at 10.5 m never counts.
    assert t.mean_neighbours == pytest.approx((30 + 91 + 41) / 91)
    assert t.ego_goal_distance == pytest.approx(30.0)
    assert t.path_crossings == 3  # agents 1, 3 (pedestrian) and 5; the cyclist's path is 10.5 m away
    assert t.ego_heading_change == 0.0 and t.lane_mult == 1.0  # no lanes in this scene


def test_saturated_terms_cap_at_one() -> None:
    s = hand_scenario(ego_goal_m=200.0)
    t = interactivity_terms(s)
    assert t.ego_goal_distance == pytest.approx(200.0)
    assert t.capped()["ego_goal_distance"] == 1.0
    low = interactivity_score(hand_scenario(ego_goal_m=50.0))  # (50 - 10) / 40 = 1: saturated
    assert interactivity_score(s) == pytest.approx(low)


@pytest.mark.parametrize("change, reason", [
    ("near_goal", "ego goal"),
    ("few_agents", "agents valid at t0"),
    ("ego_invalid", "ego is not valid at t0"),
])
def test_ineligible_tasks_get_none_not_zero(change: str, reason: str) -> None:
    s = hand_scenario()
    if change == "near_goal":
        s = hand_scenario(ego_goal_m=9.9)
    elif change == "few_agents":
        valid = np.array(s.log_valid)
        valid[4, 0] = False  # 4 agents valid at t0
        s = dataclasses.replace(s, log_valid=valid)
    else:
        valid = np.array(s.log_valid)
        valid[0, 0] = False
        s = dataclasses.replace(s, log_valid=valid)
    terms = interactivity_terms(s)
    assert not terms.eligible and reason in terms.reason
    assert interactivity_score(s) is None and terms.score is None
    assert terms.mean_neighbours >= 0.0  # terms are still reported


def test_exactly_ten_metres_and_five_agents_are_eligible() -> None:
    assert interactivity_score(hand_scenario(ego_goal_m=10.0)) is not None
    five = interactivity_terms(scene(np.stack([ego_along_x()] + [still(0, 20 * k) for k in range(1, 5)])))
    assert five.agents_valid_t0 == 5 and five.eligible  # ego goal 90 m away
    four = interactivity_terms(scene(np.stack([ego_along_x()] + [still(0, 20 * k) for k in range(1, 4)])))
    assert not four.eligible and four.score is None


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_score_is_in_unit_interval_for_random_logs(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 12))
    valid = rng.random((n, T)) < 0.8
    valid[0, :] = True
    lane = np.cumsum(rng.normal(0, 3, (30, 2)), axis=0).astype(np.float32)
    s = Scenario(
        id=f"r{seed}",
        log_xy=rng.normal(0, 20, (n, T, 2)).astype(np.float32),
        log_heading=rng.uniform(-10, 10, (n, T)).astype(np.float32),
        log_velocity=rng.normal(0, 15, (n, T, 2)).astype(np.float32),
        log_valid=valid,
        goal_xy=rng.normal(0, 60, (n, 2)).astype(np.float32),
        sizes=rng.uniform(0.5, 10, (n, 2)).astype(np.float32),
        agent_types=rng.integers(0, 4, n).astype(np.int8),
        road_points=np.concatenate([lane, lane[::-1] + 1]),
        road_offsets=np.array([0, 30, 60], np.int32),
        road_types=np.array([RoadType.LANE, RoadType.LANE], np.int8),
        ego_index=0,
    )
    terms = interactivity_terms(s)
    assert (terms.score is None) == (not terms.eligible)
    if terms.score is not None:
        assert 0.0 <= terms.score <= 1.0
    assert terms.lane_mult in (0.5, 1.0)
    for value in (terms.mean_accel_change, terms.mean_steer_change, terms.mean_neighbours,
                  terms.ego_heading_change, terms.path_crossings, terms.ttc_steps, terms.agents_near_t0):
        assert np.isfinite(value) and value >= 0.0
    assert all(0.0 <= c <= 1.0 for c in terms.capped().values())


# ----------------------------------------------------------------------------- splits
def pool() -> list[Scenario]:
    """Scenarios whose scores grow with the ego goal distance; one ineligible, one tie."""
    goals = {"g15": 15.0, "g35": 35.0, "g20": 20.0, "near": 5.0, "g30": 30.0, "g25b": 25.0, "g25a": 25.0}
    return [hand_scenario(ego_goal_m=d, sid=sid) for sid, d in goals.items()]


def test_interactive_split_picks_top_scores_with_id_tiebreak() -> None:
    scenarios = pool()
    top = interactive_split(scenarios, 4)
    assert [s.id for s in top] == ["g35", "g30", "g25a", "g25b"]
    scores = [interactivity_score(s) for s in top]
    assert scores == sorted(scores, reverse=True)
    assert [s.id for s in interactive_split(scenarios, 6)] == ["g35", "g30", "g25a", "g25b", "g20", "g15"]
    assert interactive_split(scenarios, 0) == []
    assert [s.id for s in interactive_split(list(reversed(scenarios)), 4)] == ["g35", "g30", "g25a", "g25b"]


def test_split_argument_errors() -> None:
    scenarios = pool()
    with pytest.raises(ValueError, match="n: 7 exceeds the 6 eligible"):
        interactive_split(scenarios, 7)
    with pytest.raises(ValueError, match="scenarios: empty"):
        interactive_split([], 1)
    with pytest.raises(ValueError, match="scenarios: empty"):
        random_split([], 1, seed=0)
    with pytest.raises(ValueError, match="n: 8 exceeds"):
        random_split(scenarios, 8, seed=0)
    with pytest.raises(ValueError, match="n: 7 exceeds the 6 eligible"):
        random_split(scenarios, 7, seed=0, eligible_only=True)
    with pytest.raises(ValueError, match="n: expected a non-negative integer"):
        random_split(scenarios, -1, seed=0)
    with pytest.raises(ValueError, match="n: expected"):
        interactive_split(scenarios, 2.0)  # type: ignore[arg-type]


def test_random_split_is_seeded_uniform_and_nested() -> None:
    scenarios = [hand_scenario(sid=f"s{i:02d}") for i in range(20)]
    a = random_split(scenarios, 8, seed=3)
    assert [s.id for s in a] == [s.id for s in random_split(scenarios, 8, seed=3)]
    assert len(a) == 8 and len({s.id for s in a}) == 8
    assert [s.id for s in random_split(scenarios, 5, seed=3)] == [s.id for s in a[:5]]
    others = {tuple(s.id for s in random_split(scenarios, 8, seed=k)) for k in range(4, 9)}
    assert len(others | {tuple(s.id for s in a)}) > 1  # the seed matters
    # Uniform: over many seeds every scenario is drawn about n / N of the time.
    counts = np.zeros(20)
    for seed in range(400):
        for s in random_split(scenarios, 5, seed=seed):
            counts[int(s.id[1:])] += 1
    assert np.all(np.abs(counts / 400 - 0.25) < 0.1)
    eligible = random_split(pool(), 6, seed=1, eligible_only=True)
    assert "near" not in {s.id for s in eligible}


def test_report_lists_every_scenario_in_order() -> None:
    scenarios = pool()
    report = interactivity_report(scenarios)
    assert [r.scenario_id for r in report] == [s.id for s in scenarios]
    by_id = {r.scenario_id: r for r in report}
    assert not by_id["near"].eligible and by_id["near"].score is None
    assert by_id["g35"].as_dict()["score"] == pytest.approx(interactivity_score(scenarios[1]))


# ----------------------------------------------------------------------------- WOMD tasks and folders
def test_track_tasks_one_task_per_vehicle_track() -> None:
    base = dataclasses.replace(hand_scenario(sid="scene"), tracks_to_predict=np.array([2, 0, 3, 2, 1], np.int32))
    tasks = track_tasks([base])
    assert [t.ego_index for t in tasks] == [2, 0, 1]  # pedestrian 3 left out, repeated 2 once
    assert all(t.id == "scene" and t.source == base.source for t in tasks)
    assert tasks[1] is base  # its own ego: the scenario itself
    assert tasks[0].log_xy is base.log_xy  # arrays shared, not copied
    assert [t.ego_index for t in track_tasks([base], vehicles_only=False)] == [2, 0, 3, 1]
    no_tracks = hand_scenario(sid="procedural-like")
    assert track_tasks([no_tracks]) == [no_tracks]
    walkers = dataclasses.replace(base, tracks_to_predict=np.array([3], np.int32))
    assert track_tasks([walkers]) == []
    with pytest.raises(ValueError, match=r"scenarios\[0\]: expected a Scenario"):
        track_tasks(["not a scenario"])  # type: ignore[list-item]


def scenario_doc(s: Scenario) -> dict:
    """A Scenario as a GPUDrive / PufferDrive JSON document (the fields the loader reads)."""
    kinds = {0: "vehicle", 1: "pedestrian", 2: "cyclist", 3: "other"}
    objects = [{
        "position": [{"x": float(x), "y": float(y), "z": 0.0} for x, y in s.log_xy[i]],
        "velocity": [{"x": float(x), "y": float(y)} for x, y in s.log_velocity[i]],
        "heading": [float(h) for h in s.log_heading[i]],
        "valid": [bool(v) for v in s.log_valid[i]],
        "length": float(s.sizes[i, 0]), "width": float(s.sizes[i, 1]),
        "goalPosition": {"x": float(s.goal_xy[i, 0]), "y": float(s.goal_xy[i, 1]), "z": 0.0},
        "type": kinds[int(s.agent_types[i])], "id": 1000 + i,
    } for i in range(s.num_agents)]
    roads = [{"geometry": [{"x": float(x), "y": float(y), "z": 0.0} for x, y in s.road(r)], "type": "road_edge"}
             for r in range(s.num_roads)]
    return {"scenario_id": s.id, "objects": objects, "roads": roads,
            "metadata": {"sdc_track_index": int(s.ego_index),
                         "tracks_to_predict": [{"track_index": int(k), "difficulty": 0} for k in s.tracks_to_predict]}}


def womd_folder(path: Path) -> Path:
    """Four .json.gz scenes, tracks_to_predict [0, 1, 2, 3]: egos 0 (goal varies) and 1 (12 m)
    can be eligible, ego 2 (goal 5 m) never, agent 3 is a pedestrian (no task)."""
    path.mkdir()
    for sid, goal in (("w15", 15.0), ("w35", 35.0), ("w25", 25.0), ("w05", 5.0)):
        s = dataclasses.replace(hand_scenario(ego_goal_m=goal, sid=sid),
                                tracks_to_predict=np.array([0, 1, 2, 3], np.int32))
        (path / f"{sid}.json.gz").write_bytes(gzip.compress(json.dumps(scenario_doc(s)).encode()))
    return path


def _keys(tasks: list[Scenario]) -> list[tuple[str, int]]:
    return [(t.id, t.ego_index) for t in tasks]


def test_interactive_split_of_a_folder_ranks_its_track_tasks(tmp_path: Path) -> None:
    folder = womd_folder(tmp_path / "womd")
    tasks = track_tasks(cs.load_dir(folder)[0])
    assert len(tasks) == 12  # 4 scenes x 3 vehicle tracks
    eligible = [t for t, r in zip(tasks, interactivity_report(tasks)) if r.eligible]
    assert sorted(_keys(eligible)) == sorted([(sid, 0) for sid in ("w15", "w25", "w35")]
                                             + [(sid, 1) for sid in ("w05", "w15", "w25", "w35")])
    top = interactive_split(folder, 7)
    assert _keys(top) == _keys(interactive_split(tasks, 7))
    scores = [interactivity_score(t) for t in top]
    assert None not in scores and scores == sorted(scores, reverse=True)
    assert _keys(top)[0] == ("w35", 0)  # the farthest ego goal scores highest
    assert cs.interactive_split is interactive_split and cs.track_tasks is track_tasks
    with pytest.raises(ValueError, match="n: 8 exceeds the 7 eligible tasks"):
        interactive_split(folder, 8)
    # the .npz cache is used when asked for
    assert _keys(interactive_split(folder, 3, cache_dir=tmp_path / "cache")) == _keys(top[:3])
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["w05.npz", "w15.npz", "w25.npz", "w35.npz"]
    with pytest.raises(ValueError, match="cache_dir: only used when the source is a folder"):
        interactive_split(tasks, 1, cache_dir=tmp_path / "cache")
    with pytest.raises(ValueError, match="folder does not exist"):
        interactive_split(tmp_path / "missing", 1)


def test_random_split_of_a_folder_samples_eligible_tasks(tmp_path: Path) -> None:
    folder = womd_folder(tmp_path / "womd")
    tasks = track_tasks(cs.load_dir(folder)[0])
    a = random_split(folder, 5, seed=3)
    assert _keys(a) == _keys(random_split(str(folder), 5, seed=3))  # str or Path
    assert _keys(a) == _keys(random_split(tasks, 5, seed=3, eligible_only=True))
    assert all(interactivity_score(t) is not None for t in a)
    assert len(set(_keys(a))) == 5
    assert _keys(random_split(folder, 3, seed=3)) == _keys(a)[:3]  # nested
    assert {tuple(_keys(random_split(folder, 5, seed=k))) for k in range(6)} != {tuple(_keys(a))}
    everything = random_split(folder, 12, seed=0, eligible_only=False)  # opt out: all 12 tasks
    assert sorted(_keys(everything)) == sorted(_keys(tasks))
    with pytest.raises(ValueError, match="n: 8 exceeds the 7 eligible tasks"):
        random_split(folder, 8, seed=0)


# ----------------------------------------------------------------------------- real WOMD validation scenes
def _womd_valid() -> Path:
    env = os.environ.get("CPSIM_WOMD_DIR")
    return (Path(env) if env else Path(__file__).resolve().parents[2].parent / "shared/data/womd") / "valid"


WOMD_VALID = _womd_valid()


@pytest.mark.skipif(not WOMD_VALID.is_dir(), reason=f"{WOMD_VALID} not found (set CPSIM_WOMD_DIR)")
def test_splits_of_the_real_validation_scenes() -> None:
    scenes = cs.load_dir(WOMD_VALID)[0]
    tasks = track_tasks(scenes)
    vehicle_tracks = sum(int((s.agent_types[np.unique(s.tracks_to_predict)] == AgentType.VEHICLE).sum())
                         for s in scenes)
    assert len(scenes) == 100 and len(tasks) == vehicle_tracks == 245
    assert len(set(_keys(tasks))) == len(tasks)
    top = interactive_split(tasks, 20)
    scores = [interactivity_score(t) for t in top]
    assert None not in scores and scores == sorted(scores, reverse=True)
    for t in top:  # BehaviorBench eligibility, checked from the data
        assert t.ego_index in t.tracks_to_predict and t.agent_types[t.ego_index] == AgentType.VEHICLE
        assert t.log_valid[t.ego_index, 0] and t.log_valid[:, 0].sum() >= 5
        assert np.linalg.norm(t.goal_xy[t.ego_index] - t.log_xy[t.ego_index, 0]) >= 10.0
    rand = random_split(tasks, 20, seed=0, eligible_only=True)
    assert all(interactivity_score(t) is not None for t in rand) and len(set(_keys(rand))) == 20
    assert _keys(rand) == _keys(random_split(tasks, 20, seed=0, eligible_only=True))
