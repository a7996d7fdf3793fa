"""Conditioned reward (BehaviorBench's, term by term), as a Warp function with a NumPy reference.

Per tracked agent and step, with the agent's raw condition c (``cpsim.conditions`` order:
alpha weights), dt the decision period (s), v the signed speed (m/s), the nearest lane
centreline within ``lane_radius`` (heading error th rad; th = pi when no lane is near;
lateral offset x m, *right* positive as BehaviorBench measures it; our lane query reports
left positive), b = c.center_bias (m, positive keeps right) and the comfort violations n
of the step:

=========== ============================================================ ===========================
term        raw                                                          weighted (summed)
=========== ============================================================ ===========================
goal        1 on the step the goal is first reached, 0 if the agent      + raw
            also collides in that step
collision   1 while in collision this step                               - (c.collision + 0.1 |v|) raw
offroad     1 when off-road this step                                    - c.offroad raw
comfort     n = 1{|a_long|>3} + 1{|a_lat|>3} + 1{|j_long|>5 or |j_lat|>5} - c.comfort raw
lane_align  min(cos th, 0) + 0.0025 (1 - |th| / (pi/2))                  + c.lane_align dt raw
vel_align   min(|v| cos th, 0)                                           + c.lane_align c.vel_align dt raw
lane_center with a lane near: 1{cos th > 0.5} |x - b|                    - c.lane_center dt raw
            - 0.05 exp(0.5 - |x - b|); else 0
reverse     1{v < 0}                                                     - c.reverse dt raw
velocity    max(cos th, 0) while |v| > 2.5 m/s and a lane is near        + 0.0025 dt raw
time        1 while moving or accelerating (|v| or |a_long| > 1e-3)      - 2.5e-5 dt raw
=========== ============================================================ ===========================

The reward is the sum of the weighted terms; agents not present in the step get 0 for all.
Goal, collision, off-road and comfort are not multiplied by dt, the lane, reversing,
velocity and time terms are (BehaviorBench's ``c_step``). The per-step lane terms are thus
about 1e-3 of the goal's +1: the return is dominated by the task (goal, collision,
off-road), so a critic trained on it values the task, not the style penalties still to pay.
Nothing penalises standing still, and a timeout returns 0. BehaviorBench's trainer clamps
each step's reward to [-1, 1]; here that is a learner option
(``CounterPlay(clip_reward=1.0)``), so that the simulator's reward stays the conditioned
sum that evaluation and search rank by.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from cpsim.scoring import COMFORT_A_LAT, COMFORT_A_LONG, COMFORT_JERK, count_comfort_violations
from cpsim.state import NUM_REWARD_TERMS, REWARD_TERMS

# condition field indices (cpsim.conditions.CONDITION_FIELDS order)
C_GOAL_RADIUS, C_GOAL_SPEED, C_COLLISION, C_OFFROAD, C_COMFORT, C_LANE_ALIGN, C_VEL_ALIGN, \
    C_LANE_CENTER, C_CENTER_BIAS, C_REVERSE = range(10)
#: Comfort thresholds (m/s^2, m/s^2, m/s^3) as Warp constants, built from the Python values
#: of :mod:`cpsim.scoring` (COMFORT_A_LONG, COMFORT_A_LAT, COMFORT_JERK): one source.
WP_COMFORT_A_LONG = wp.constant(COMFORT_A_LONG)
WP_COMFORT_A_LAT = wp.constant(COMFORT_A_LAT)
WP_COMFORT_JERK = wp.constant(COMFORT_JERK)
#: Weight of the alignment bonus inside the lane-alignment term (BehaviorBench).
ALIGN_BONUS = 0.0025
#: Centring bonus: 0.05 exp(0.5 - |x - b|) (BehaviorBench).
CENTER_BONUS = 0.05
CENTER_BONUS_WIDTH = 0.5
#: Velocity reward: weight and the speed above which it pays (m/s).
VELOCITY_REWARD = 0.0025
VELOCITY_MIN_SPEED = 2.5
#: Time term: weight, and the speed / acceleration below which an agent counts as standing.
TIME_PENALTY = 2.5e-5
MOVING_EPS = 1.0e-3
#: Collision penalty per m/s of the agent's speed.
COLLISION_SPEED_COEF = 0.1

WP_ALIGN_BONUS = wp.constant(ALIGN_BONUS)
WP_CENTER_BONUS = wp.constant(CENTER_BONUS)
WP_CENTER_BONUS_WIDTH = wp.constant(CENTER_BONUS_WIDTH)
WP_VELOCITY_REWARD = wp.constant(VELOCITY_REWARD)
WP_VELOCITY_MIN_SPEED = wp.constant(VELOCITY_MIN_SPEED)
WP_TIME_PENALTY = wp.constant(TIME_PENALTY)
WP_MOVING_EPS = wp.constant(MOVING_EPS)
WP_COLLISION_SPEED_COEF = wp.constant(COLLISION_SPEED_COEF)
WP_HALF_PI = wp.constant(0.5 * math.pi)


@wp.func
def comfort_violations(a_long: float, a_lat: float, jerk: float, lat_jerk: float) -> int:
    """Comfort violations of a step (0..3): 1{|a_long| > 3} + 1{|a_lat| > 3} + 1{|jerk| > 5},
    where the jerk test counts the longitudinal or the lateral jerk (BehaviorBench); the
    thresholds are those of :mod:`cpsim.scoring`."""
    n = int(0)
    if wp.abs(a_long) > WP_COMFORT_A_LONG:
        n += 1
    if wp.abs(a_lat) > WP_COMFORT_A_LAT:
        n += 1
    if wp.abs(jerk) > WP_COMFORT_JERK or wp.abs(lat_jerk) > WP_COMFORT_JERK:
        n += 1
    return n


def comfort_violations_np(a_long, a_lat, jerk, lat_jerk) -> np.ndarray:
    """Reference of :func:`comfort_violations` over arrays (int32)."""
    return count_comfort_violations(a_long, a_lat, jerk, lat_jerk)


@wp.func
def write_reward(conds: wp.array3d(dtype=wp.float32), raw: wp.array3d(dtype=wp.float32),
                 weighted: wp.array3d(dtype=wp.float32), w: int, a: int,
                 goal_now: bool, collided: bool, offroad: bool, violations: int, has_lane: bool,
                 err: float, offset: float, speed: float, accel: float, dt: float) -> float:
    """Compute every term into raw[w, a, :] and weighted[w, a, :]; returns the reward.

    ``offset`` is the lane query's lateral offset (m, left positive), ``err`` its heading
    error (rad); both are ignored when ``has_lane`` is False (th = pi then)."""
    r_goal = float(0.0)
    if goal_now and not collided:
        r_goal = 1.0
    r_col = float(0.0)
    if collided:
        r_col = 1.0
    r_off = float(0.0)
    if offroad:
        r_off = 1.0
    r_comfort = float(violations)
    th = float(wp.pi)
    if has_lane:
        th = err
    ce = wp.cos(th)
    r_align = wp.min(ce, 0.0) + WP_ALIGN_BONUS * (1.0 - wp.abs(th) / WP_HALF_PI)
    r_vel = wp.min(wp.abs(speed) * ce, 0.0)
    r_center = float(0.0)
    if has_lane:
        d = wp.abs(-offset - conds[w, a, 8])
        if ce > 0.5:
            r_center = d
        r_center = r_center - WP_CENTER_BONUS * wp.exp(WP_CENTER_BONUS_WIDTH - d)
    r_rev = float(0.0)
    if speed < 0.0:
        r_rev = 1.0
    r_velocity = float(0.0)
    if has_lane and wp.abs(speed) > WP_VELOCITY_MIN_SPEED:
        r_velocity = wp.max(ce, 0.0)
    r_time = float(0.0)
    if wp.abs(speed) > WP_MOVING_EPS or wp.abs(accel) > WP_MOVING_EPS:
        r_time = 1.0
    raw[w, a, 0] = r_goal
    raw[w, a, 1] = r_col
    raw[w, a, 2] = r_off
    raw[w, a, 3] = r_comfort
    raw[w, a, 4] = r_align
    raw[w, a, 5] = r_vel
    raw[w, a, 6] = r_center
    raw[w, a, 7] = r_rev
    raw[w, a, 8] = r_velocity
    raw[w, a, 9] = r_time
    w_goal = r_goal
    w_col = -(conds[w, a, 2] + WP_COLLISION_SPEED_COEF * wp.abs(speed)) * r_col
    w_off = -conds[w, a, 3] * r_off
    w_comfort = -conds[w, a, 4] * r_comfort
    w_align = conds[w, a, 5] * dt * r_align
    w_vel = conds[w, a, 5] * conds[w, a, 6] * dt * r_vel
    w_center = -conds[w, a, 7] * dt * r_center
    w_rev = -conds[w, a, 9] * dt * r_rev
    w_velocity = WP_VELOCITY_REWARD * dt * r_velocity
    w_time = -WP_TIME_PENALTY * dt * r_time
    weighted[w, a, 0] = w_goal
    weighted[w, a, 1] = w_col
    weighted[w, a, 2] = w_off
    weighted[w, a, 3] = w_comfort
    weighted[w, a, 4] = w_align
    weighted[w, a, 5] = w_vel
    weighted[w, a, 6] = w_center
    weighted[w, a, 7] = w_rev
    weighted[w, a, 8] = w_velocity
    weighted[w, a, 9] = w_time
    return w_goal + w_col + w_off + w_comfort + w_align + w_vel + w_center + w_rev + w_velocity + w_time


def reward_terms_np(condition: np.ndarray, *, goal_now, collided, offroad, violations, has_lane, err, offset,
                    speed, accel=0.0, dt: float = 0.1) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray],
                                                                 np.ndarray]:
    """Reference of :func:`write_reward` in float64, vectorised: every argument broadcasts
    (scalars for one agent, arrays for a rollout); ``condition`` is (..., 10) raw.

    Returns (raw terms, weighted terms, reward), each term an array of the broadcast shape.
    """
    c = np.asarray(condition, np.float64)
    goal_now, collided, offroad, has_lane = (np.asarray(x, bool) for x in (goal_now, collided, offroad, has_lane))
    violations = np.asarray(violations, np.float64)
    speed = np.asarray(speed, np.float64)
    accel = np.asarray(accel, np.float64)
    th = np.where(has_lane, np.asarray(err, np.float64), np.pi)
    ce = np.cos(th)
    d = np.abs(-np.asarray(offset, np.float64) - c[..., C_CENTER_BIAS])
    raw = {
        "goal": (goal_now & ~collided).astype(np.float64),
        "collision": collided.astype(np.float64),
        "offroad": offroad.astype(np.float64),
        "comfort": violations,
        "lane_align": np.minimum(ce, 0.0) + ALIGN_BONUS * (1.0 - np.abs(th) / (0.5 * np.pi)),
        "vel_align": np.minimum(np.abs(speed) * ce, 0.0),
        "lane_center": np.where(has_lane, np.where(ce > 0.5, d, 0.0)
                                - CENTER_BONUS * np.exp(CENTER_BONUS_WIDTH - d), 0.0),
        "reverse": (speed < 0.0).astype(np.float64),
        "velocity": np.where(has_lane & (np.abs(speed) > VELOCITY_MIN_SPEED), np.maximum(ce, 0.0), 0.0),
        "time": ((np.abs(speed) > MOVING_EPS) | (np.abs(accel) > MOVING_EPS)).astype(np.float64),
    }
    wt = {
        "goal": raw["goal"],
        "collision": -(c[..., C_COLLISION] + COLLISION_SPEED_COEF * np.abs(speed)) * raw["collision"],
        "offroad": -c[..., C_OFFROAD] * raw["offroad"],
        "comfort": -c[..., C_COMFORT] * raw["comfort"],
        "lane_align": c[..., C_LANE_ALIGN] * dt * raw["lane_align"],
        "vel_align": c[..., C_LANE_ALIGN] * c[..., C_VEL_ALIGN] * dt * raw["vel_align"],
        "lane_center": -c[..., C_LANE_CENTER] * dt * raw["lane_center"],
        "reverse": -c[..., C_REVERSE] * dt * raw["reverse"],
        "velocity": VELOCITY_REWARD * dt * raw["velocity"],
        "time": -TIME_PENALTY * dt * raw["time"],
    }
    return raw, wt, sum(wt.values())


assert NUM_REWARD_TERMS == 10
__all__ = ["write_reward", "comfort_violations", "comfort_violations_np", "reward_terms_np", "REWARD_TERMS"]
