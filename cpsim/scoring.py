"""BehaviorBench episode scores from the simulator's metric accumulators (pure NumPy).

The simulator accumulates, per agent and episode, ``sim.metrics`` (:data:`cpsim.state.METRIC_FIELDS`):
steps alive, comfort violations, aligned steps, the lateral-offset sum, the first
collision / off-road / goal steps and the at-fault flag. This module turns them into the
per-episode quantities of the seed paper:

* comfort = 1 - min(violations / (3 T), 1), ``T`` = steps alive;
* lane_align = aligned steps / T;
* lane_center = 1 - min(mean lateral distance / 2 m, 1);
* score = 0 when the agent missed its goal, had an at-fault collision or went off-road;
  otherwise 100 * (0.2 comfort + 0.5 lane_align + 0.3 lane_center).

One implementation serves the Gymnasium / SB3 front-ends (episode-end ``info``) and the
evaluation (:mod:`cpalgo.evaluate.metrics` re-exports these names).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

#: Comfort thresholds of a step (BehaviorBench): |a_long| m/s^2, |a_lat| m/s^2 and |jerk|
#: m/s^3 (longitudinal or lateral). The one source of these values: the simulator's Warp
#: function (``cpsim.kernels.reward.comfort_violations``, through Warp constants built from
#: them), :func:`count_comfort_violations` and the evaluation (``cpalgo.evaluate.metrics``).
COMFORT_A_LONG = 3.0
COMFORT_A_LAT = 3.0
COMFORT_JERK = 5.0
#: Number of comfort checks per step (the 3 in 3 T).
COMFORT_CHECKS_PER_STEP = 3
#: Mean lateral distance (m) at which lane_center reaches 0.
LANE_CENTER_CLAMP = 2.0
#: Score weights (comfort, lane_align, lane_center), the seed paper's.
SCORE_WEIGHTS = (0.2, 0.5, 0.3)
#: Lateral distance (m) the lane query records when the scenario's map holds no lane at all
#: (lane_center is 0 then). The one source of this value: the simulator's Warp lane query
#: (``cpsim.kernels.geometry``, through a Warp constant built from it), its NumPy reference
#: and the evaluation (``cpalgo.evaluate.metrics``).
NO_LANE_DISTANCE = 1000.0


def _as_float(x: np.ndarray | float, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return a


def count_comfort_violations(a_long, a_lat, jerk, lat_jerk=0.0) -> np.ndarray:
    """Comfort violations per step (0..3, int32) of (...,) arrays:
    1{|a_long| > COMFORT_A_LONG} + 1{|a_lat| > COMFORT_A_LAT} + 1{|jerk| or |lat_jerk| > COMFORT_JERK}
    (the NumPy twin of the simulator's Warp function; no input checks)."""
    a_long, a_lat, jerk, lat_jerk = (np.asarray(x, np.float64) for x in (a_long, a_lat, jerk, lat_jerk))
    return ((np.abs(a_long) > COMFORT_A_LONG).astype(np.int32) + (np.abs(a_lat) > COMFORT_A_LAT)
            + ((np.abs(jerk) > COMFORT_JERK) | (np.abs(lat_jerk) > COMFORT_JERK))).astype(np.int32)


def metrics_from_accumulators(
    steps_alive: np.ndarray,
    comfort_violation_count: np.ndarray,
    aligned_steps: np.ndarray,
    lateral_offset_sum: np.ndarray,
) -> dict[str, np.ndarray]:
    """Comfort, lane alignment and lane centring from per-task accumulators.

    These are the simulator's ``metrics`` accumulators read at the end of the episode.

    Args:
        steps_alive: (...,) number of steps the ego was alive, ``T``.
        comfort_violation_count: (...,) total comfort violations over those steps.
        aligned_steps: (...,) number of aligned steps.
        lateral_offset_sum: (...,) sum over alive steps of the lateral distance, m.
    Returns:
        dict with ``comfort``, ``lane_align``, ``lane_center``: (...,) float64 in [0, 1].
        Tasks with ``T == 0`` get 0 for all three (nothing was driven).
    """
    t = _as_float(steps_alive, "steps_alive")
    viol = _as_float(comfort_violation_count, "comfort_violations")
    aligned = _as_float(aligned_steps, "aligned_steps")
    lat = _as_float(lateral_offset_sum, "lateral_offset_sum")
    if np.any(t < 0) or np.any(viol < 0) or np.any(aligned < 0) or np.any(lat < 0):
        raise ValueError("accumulators must be non-negative")
    if np.any(aligned > t):
        raise ValueError("aligned_steps: larger than steps_alive")
    alive = t > 0
    safe_t = np.where(alive, t, 1.0)
    comfort = 1.0 - np.minimum(viol / (COMFORT_CHECKS_PER_STEP * safe_t), 1.0)
    lane_align = aligned / safe_t
    lane_center = 1.0 - np.minimum((lat / safe_t) / LANE_CENTER_CLAMP, 1.0)
    zero = np.zeros_like(t)
    return {
        "comfort": np.where(alive, comfort, zero),
        "lane_align": np.where(alive, lane_align, zero),
        "lane_center": np.where(alive, lane_center, zero),
    }


def task_score(
    goal: np.ndarray,
    at_fault_collision: np.ndarray,
    offroad: np.ndarray,
    comfort: np.ndarray,
    lane_align: np.ndarray,
    lane_center: np.ndarray,
) -> np.ndarray:
    """BehaviorBench task score, 0-100 (float64, shape of the broadcast inputs).

    0 when the ego missed its goal, had an at-fault collision or went off-road;
    otherwise ``100 * (0.2 comfort + 0.5 lane_align + 0.3 lane_center)``.
    """
    wc, wa, wl = SCORE_WEIGHTS
    c, a, lc = (_as_float(v, n) for v, n in ((comfort, "comfort"), (lane_align, "lane_align"),
                                             (lane_center, "lane_center")))
    for v, n in ((c, "comfort"), (a, "lane_align"), (lc, "lane_center")):
        if np.any((v < -1e-9) | (v > 1 + 1e-9)):
            raise ValueError(f"{n}: values must lie in [0, 1]")
    success = np.asarray(goal, bool) & ~np.asarray(at_fault_collision, bool) & ~np.asarray(offroad, bool)
    return np.where(success, 100.0 * (wc * c + wa * a + wl * lc), 0.0)


def episode_scores(metrics: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Events and scores of finished episodes from the simulator's accumulators.

    Args:
        metrics: ``sim.metrics`` read as NumPy arrays and indexed down to the agents of
            interest (any common shape).
    Returns:
        (same shape) ``goal``, ``collision``, ``at_fault_collision``, ``offroad``,
        ``timeout`` (bool) and ``comfort``, ``lane_align``, ``lane_center`` ([0, 1]),
        ``score`` (0-100) (float64). Events come from the accumulators rather than the
        sticky outcome: an agent that is not removed by its first event (a replayed expert)
        may reach its goal and collide later, and the score must see both.
    """
    goal = np.asarray(metrics["goal_step"]) >= 0
    collision = np.asarray(metrics["first_collision_step"]) >= 0
    offroad = np.asarray(metrics["first_offroad_step"]) >= 0
    fault = collision & np.asarray(metrics["at_fault"]).astype(bool)
    acc = metrics_from_accumulators(metrics["steps_alive"], metrics["comfort_violations"],
                                    metrics["aligned_steps"], metrics["lateral_offset_sum"])
    return {
        "goal": goal, "collision": collision, "at_fault_collision": fault, "offroad": offroad,
        "timeout": ~(goal | collision | offroad), **acc,
        "score": task_score(goal, fault, offroad, acc["comfort"], acc["lane_align"], acc["lane_center"]),
    }


__all__ = ["COMFORT_A_LONG", "COMFORT_A_LAT", "COMFORT_JERK", "count_comfort_violations", "COMFORT_CHECKS_PER_STEP", "LANE_CENTER_CLAMP", "SCORE_WEIGHTS", "metrics_from_accumulators",
           "task_score", "episode_scores"]
