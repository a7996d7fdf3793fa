"""Conditioned reward (GigaFlow-style), as a Warp function with a NumPy reference.

Per agent and step, with the agent's raw condition c (``cpsim.conditions`` order), the
signed speed v (m/s), the nearest lane within ``lane_radius`` (heading error e rad, signed
lateral offset o m, left positive) and the comfort violations of the step:

=========== ================================================ ===================================
term        raw                                              weighted (added to the reward)
=========== ================================================ ===================================
goal        1 on the step the goal is first reached          + raw
collision   1 while in collision this step                   - (c.collision + 0.1 |v|) raw
offroad     1 when off-road this step                        - c.offroad raw
comfort     1{|a_long|>3} + 1{|a_lat|>3} + 1{|jerk|>5}       - c.comfort raw
            (jerk: longitudinal or lateral)
lane_align  cos(e) - 1 with a lane near, else -1           + c.lane_align raw
lane_center -min(|o - target|, lane_radius) with a lane      + c.lane_center raw
            near, else -lane_radius; target = -center_bias
            x lane_width (positive bias keeps right)
vel_align   -|v| (1 - cos e) / 20 with a lane near, else 0   + c.vel_align raw
reverse     max(-v, 0)                                       - c.reverse raw
step        1                                                - step_penalty raw
progress    metres the agent got closer to its goal this     + progress_coef x aggression raw
            step (task agents with a lane near; 0 otherwise) (aggression = clip(1 - c.collision
                                                             / 3, 0, 1); progress_coef of
                                                             SimConfig, default 0)
=========== ================================================ ===================================

The reward is the sum of the weighted terms. Agents not present in the step get 0 for all.
Every per-step term but progress is a penalty (<= 0) and only reaching the goal pays: agents
leave the episode at their goal, so a positive per-step term (e.g. alignment as ``+cos e``)
would pay them for staying on the road instead of finishing, and self-play would learn to
wait. Progress pays only for getting closer to the goal (moving away costs the same), so it
cannot be farmed by staying, and only near a lane, so that cutting a corner across the grass
earns nothing (without that gate, 0.05 raised the Interactive off-road rate from 4 % to 21 %); it is off by default and, when on, scaled by the condition's
collision weight, so that bold styles are paid every step for going and normal and cautious
(collision weight 3) are not.
"""

from __future__ import annotations

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
#: Speed scale of the velocity-alignment term (m/s).
VEL_ALIGN_SCALE = 20.0
#: Collision weight at which the progress term's aggression factor reaches 0 (p_train's top).
PROGRESS_COLLISION_SCALE = 3.0
WP_PROGRESS_COLLISION_SCALE = wp.constant(PROGRESS_COLLISION_SCALE)


@wp.func
def aggression(collision_weight: float) -> float:
    """Style factor of the progress term: clip(1 - collision_weight / 3, 0, 1)."""
    return wp.clamp(1.0 - collision_weight / WP_PROGRESS_COLLISION_SCALE, 0.0, 1.0)


def aggression_np(collision_weight) -> np.ndarray:
    """Reference of :func:`aggression` over arrays (float64)."""
    return np.clip(1.0 - np.asarray(collision_weight, np.float64) / PROGRESS_COLLISION_SCALE, 0.0, 1.0)


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
                 err: float, offset: float, speed: float, lane_radius: float, lane_width: float,
                 step_penalty: float, progress: float, progress_coef: float) -> float:
    """Compute every term into raw[w, a, :] and weighted[w, a, :]; returns the reward."""
    r_goal = float(0.0)
    if goal_now:
        r_goal = 1.0
    r_col = float(0.0)
    if collided:
        r_col = 1.0
    r_off = float(0.0)
    if offroad:
        r_off = 1.0
    r_comfort = float(violations)
    r_align = float(-1.0)
    r_center = -lane_radius
    r_vel = float(0.0)
    if has_lane:
        ce = wp.cos(err)
        r_align = ce - 1.0
        target = -conds[w, a, 8] * lane_width
        r_center = -wp.min(wp.abs(offset - target), lane_radius)
        r_vel = -wp.abs(speed) * (1.0 - ce) / 20.0
    r_rev = wp.max(-speed, 0.0)
    raw[w, a, 0] = r_goal
    raw[w, a, 1] = r_col
    raw[w, a, 2] = r_off
    raw[w, a, 3] = r_comfort
    raw[w, a, 4] = r_align
    raw[w, a, 5] = r_center
    raw[w, a, 6] = r_vel
    raw[w, a, 7] = r_rev
    raw[w, a, 8] = 1.0
    raw[w, a, 9] = progress
    w_goal = r_goal
    w_col = -(conds[w, a, 2] + 0.1 * wp.abs(speed)) * r_col
    w_off = -conds[w, a, 3] * r_off
    w_comfort = -conds[w, a, 4] * r_comfort
    w_align = conds[w, a, 5] * r_align
    w_center = conds[w, a, 7] * r_center
    w_vel = conds[w, a, 6] * r_vel
    w_rev = -conds[w, a, 9] * r_rev
    w_step = -step_penalty
    w_progress = progress_coef * aggression(conds[w, a, 2]) * progress
    weighted[w, a, 0] = w_goal
    weighted[w, a, 1] = w_col
    weighted[w, a, 2] = w_off
    weighted[w, a, 3] = w_comfort
    weighted[w, a, 4] = w_align
    weighted[w, a, 5] = w_center
    weighted[w, a, 6] = w_vel
    weighted[w, a, 7] = w_rev
    weighted[w, a, 8] = w_step
    weighted[w, a, 9] = w_progress
    return w_goal + w_col + w_off + w_comfort + w_align + w_center + w_vel + w_rev + w_step + w_progress


def reward_terms_np(condition: np.ndarray, *, goal_now: bool, collided: bool, offroad: bool,
                    violations: int, has_lane: bool, err: float, offset: float, speed: float,
                    lane_radius: float = 4.0, lane_width: float = 3.7,
                    step_penalty: float = 1e-4, progress: float = 0.0,
                    progress_coef: float = 0.0) -> tuple[dict[str, float], dict[str, float], float]:
    """Reference of :func:`write_reward` for one agent: (raw, weighted, reward)."""
    c = np.asarray(condition, np.float64)
    raw = dict.fromkeys(REWARD_TERMS, 0.0)
    raw["goal"] = float(goal_now)
    raw["collision"] = float(collided)
    raw["offroad"] = float(offroad)
    raw["comfort"] = float(violations)
    raw["lane_center"] = -lane_radius
    raw["lane_align"] = -1.0
    if has_lane:
        raw["lane_align"] = float(np.cos(err)) - 1.0
        raw["lane_center"] = -min(abs(offset + c[C_CENTER_BIAS] * lane_width), lane_radius)
        raw["vel_align"] = -abs(speed) * (1 - np.cos(err)) / VEL_ALIGN_SCALE
    raw["reverse"] = max(-speed, 0.0)
    raw["step"] = 1.0
    raw["progress"] = float(progress)
    wt = {
        "goal": raw["goal"],
        "collision": -(c[C_COLLISION] + 0.1 * abs(speed)) * raw["collision"],
        "offroad": -c[C_OFFROAD] * raw["offroad"],
        "comfort": -c[C_COMFORT] * raw["comfort"],
        "lane_align": c[C_LANE_ALIGN] * raw["lane_align"],
        "lane_center": c[C_LANE_CENTER] * raw["lane_center"],
        "vel_align": c[C_VEL_ALIGN] * raw["vel_align"],
        "reverse": -c[C_REVERSE] * raw["reverse"],
        "step": -step_penalty,
        "progress": progress_coef * float(aggression_np(c[C_COLLISION])) * raw["progress"],
    }
    return raw, wt, float(sum(wt.values()))


assert NUM_REWARD_TERMS == 10
__all__ = ["write_reward", "aggression", "aggression_np", "comfort_violations", "comfort_violations_np", "reward_terms_np", "REWARD_TERMS"]
