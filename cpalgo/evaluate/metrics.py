"""BehaviorBench-style per-task metrics, pure NumPy and vectorised over tasks.

Definitions (``../shared/DESIGN.md``, Evaluation; the seed paper's weights):

* ``T`` = steps the ego was alive (decisions taken before it was removed or the episode ended).
* comfort = 1 - min(violations / (3 T), 1), where every step adds
  1{|a_long| > 3 m/s^2} + 1{|a_lat| > 3 m/s^2} + 1{|jerk| > 5 m/s^3}, the jerk test counting
  the longitudinal or the lateral jerk.
* lane_align = aligned steps / T; a step is aligned when a lane centreline lies within
  4 m and the heading error to it is below 15 degrees.
* lane_center = 1 - min(mean lateral distance / 2 m, 1); the lateral distance is the true
  point-to-segment distance to the nearest lane centreline (however far it is).
* score = 0 when the ego misses its goal, has an at-fault collision or goes off-road;
  otherwise 100 * (0.2 comfort + 0.5 lane_align + 0.3 lane_center).

At-fault collisions are classified by the simulator (one implementation: the Warp kernel of
``cpsim.kernels.geometry``, BehaviorBench's rules on the state one step before contact; its
NumPy references there serve the tests) and read from its ``at_fault`` accumulator.

Every function takes arrays with arbitrary leading "task" dimensions and works on all
of them at once; nothing loops over tasks in Python.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Mapping

import numpy as np

# the per-episode scores live with the simulator (the env infos report them too); re-exported
from cpsim.scoring import COMFORT_CHECKS_PER_STEP as COMFORT_CHECKS_PER_STEP
from cpsim.scoring import LANE_CENTER_CLAMP as LANE_CENTER_CLAMP
from cpsim.scoring import NO_LANE_DISTANCE as NO_LANE_DISTANCE
from cpsim.scoring import SCORE_WEIGHTS as SCORE_WEIGHTS
from cpsim.scoring import count_comfort_violations
from cpsim.scoring import episode_scores as episode_scores
from cpsim.scoring import metrics_from_accumulators as metrics_from_accumulators
from cpsim.scoring import task_score as task_score

# ----------------------------------------------------------------------------- constants
# comfort thresholds: cpsim.scoring.COMFORT_A_LONG / COMFORT_A_LAT / COMFORT_JERK (the
# simulator's values; comfort_violations below counts with them)
#: Lane queries: search radius (m) and alignment tolerance (deg); lane_center uses the true
#: distance whatever the radius (NO_LANE_DISTANCE only when a map has no lane at all).
LANE_SEARCH_RADIUS = 4.0
ALIGN_MAX_HEADING_ERROR_DEG = 15.0


class OutcomeClass(IntEnum):
    """Outcome classes of the failure-repair analysis, in priority order (lowest wins)."""

    AT_FAULT_COLLISION = 0
    OFFROAD = 1
    COMPLETED = 2
    NON_AT_FAULT_COLLISION = 3
    TIMEOUT = 4


OUTCOME_CLASS_NAMES: tuple[str, ...] = tuple(c.name.lower() for c in OutcomeClass)


# ----------------------------------------------------------------------------- helpers
def _as_float(x: np.ndarray | float, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return a


def _as_bool(x: np.ndarray | bool) -> np.ndarray:
    return np.asarray(x, dtype=bool)


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Wrap angles (rad) to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


# ----------------------------------------------------------------------------- comfort
def comfort_violations(a_long: np.ndarray, a_lat: np.ndarray, jerk: np.ndarray,
                       lat_jerk: np.ndarray | float = 0.0) -> np.ndarray:
    """Violations per step (0..3): 1{|a_long|>3} + 1{|a_lat|>3} + 1{|jerk|>5 or |lat_jerk|>5}.

    Args:
        a_long, a_lat: (...,) longitudinal / lateral acceleration, m/s^2.
        jerk, lat_jerk: (...,) longitudinal / lateral jerk, m/s^3 (BehaviorBench counts a
            step whose longitudinal or lateral jerk exceeds the limit).
    Returns:
        (...,) int32 count of violated comfort limits.
    """
    return count_comfort_violations(_as_float(a_long, "a_long"), _as_float(a_lat, "a_lat"),
                                    _as_float(jerk, "jerk"), _as_float(lat_jerk, "lat_jerk"))


# ----------------------------------------------------------------------------- from trajectories
def metrics_from_steps(
    alive: np.ndarray,
    a_long: np.ndarray,
    a_lat: np.ndarray,
    jerk: np.ndarray,
    aligned: np.ndarray,
    lateral_offset: np.ndarray,
    lat_jerk: np.ndarray | float = 0.0,
) -> dict[str, np.ndarray]:
    """Comfort, lane alignment and lane centring from per-step signals.

    Args (all (..., T); steps where ``alive`` is False are ignored):
        alive: bool, the ego existed at that step.
        a_long, a_lat: m/s^2. jerk, lat_jerk: longitudinal / lateral jerk, m/s^3.
        aligned: bool, lane-aligned at that step.
        lateral_offset: m, distance to the nearest lane centreline.
    Returns:
        The same dict as :func:`metrics_from_accumulators`, plus the accumulators
        themselves (``steps_alive``, ``comfort_violations``, ``aligned_steps``,
        ``lateral_offset_sum``) so both paths can be compared.
    """
    alive = _as_bool(alive)
    viol = np.where(alive, comfort_violations(a_long, a_lat, jerk, lat_jerk), 0)
    lat = np.where(alive, _as_float(lateral_offset, "lateral_offset"), 0.0)
    acc = {
        "steps_alive": alive.sum(axis=-1),
        "comfort_violations": viol.sum(axis=-1),
        "aligned_steps": (alive & _as_bool(aligned)).sum(axis=-1),
        "lateral_offset_sum": lat.sum(axis=-1),
    }
    out = metrics_from_accumulators(
        acc["steps_alive"], acc["comfort_violations"], acc["aligned_steps"], acc["lateral_offset_sum"]
    )
    return {**acc, **out}


def kinematics_from_poses(
    xy: np.ndarray, heading: np.ndarray, dt: float = 0.1
) -> dict[str, np.ndarray]:
    """Speed, accelerations and jerk by finite differences of a pose trajectory.

    Args:
        xy: (..., T, 2) positions, m. heading: (..., T) rad. dt: step, s.
    Returns:
        dict of (..., T) float64 arrays: ``speed`` (signed along the heading, m/s),
        ``a_long`` (m/s^2), ``a_lat`` = speed * yaw rate (m/s^2), ``jerk`` (d a_long / dt,
        m/s^3), ``lat_jerk`` (d a_lat / dt, m/s^3). Step 0 uses the first available
        difference (backward differences elsewhere), so a constant-acceleration trajectory
        gives a constant ``a_long``.
    """
    xy = _as_float(xy, "xy")
    heading = _as_float(heading, "heading")
    if xy.shape[-1] != 2 or xy.shape[:-1] != heading.shape or heading.shape[-1] < 4:
        raise ValueError(f"xy (...,T,2) and heading (...,T) with T >= 4; got {xy.shape}, {heading.shape}")
    d = np.diff(xy, axis=-2) / dt  # (..., T-1, 2) velocity between steps
    mid_heading = heading[..., :-1] + 0.5 * wrap_angle(np.diff(heading, axis=-1))
    v = d[..., 0] * np.cos(mid_heading) + d[..., 1] * np.sin(mid_heading)  # (..., T-1)
    yaw_rate = wrap_angle(np.diff(heading, axis=-1)) / dt
    speed = np.concatenate([v[..., :1], v], axis=-1)
    a = np.diff(v, axis=-1) / dt  # (..., T-2)
    a_long = np.concatenate([a[..., :1], a[..., :1], a], axis=-1)
    j = np.diff(a, axis=-1) / dt  # (..., T-3)
    jerk = np.concatenate([j[..., :1], j[..., :1], j[..., :1], j], axis=-1)
    a_lat = speed * np.concatenate([yaw_rate[..., :1], yaw_rate], axis=-1)
    lj = np.diff(a_lat, axis=-1) / dt  # (..., T-1)
    lat_jerk = np.concatenate([lj[..., :1], lj], axis=-1)
    return {"speed": speed, "a_long": a_long, "a_lat": a_lat, "jerk": jerk, "lat_jerk": lat_jerk}


def lane_segments(road_points: np.ndarray, road_offsets: np.ndarray, road_types: np.ndarray,
                  lane_type: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Lane-centreline segments of a scenario's road network.

    Args:
        road_points (P, 2), road_offsets (R+1,), road_types (R,): as in :class:`cpsim.Scenario`.
        lane_type: the ``RoadType`` code of lane centrelines (``RoadType.LANE`` = 0).
    Returns:
        segments (S, 4) float64 ``(x0, y0, x1, y1)`` in polyline order (direction of
        travel) and lane_ids (S,) int64, the polyline index each segment belongs to.
    """
    pts = np.asarray(road_points, np.float64)
    offs = np.asarray(road_offsets, np.int64)
    types = np.asarray(road_types)
    starts, ends = offs[:-1], offs[1:]
    is_lane = (types == lane_type) & (ends - starts >= 2)
    # segment k of polyline r joins points k and k+1 with starts[r] <= k < ends[r] - 1
    counts = np.where(is_lane, ends - starts - 1, 0)
    lane_ids = np.repeat(np.arange(len(types)), counts)
    first = np.repeat(starts, counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    k = first + local
    segs = np.concatenate([pts[k], pts[k + 1]], axis=-1) if k.size else np.zeros((0, 4))
    return segs, lane_ids


def lane_queries(xy: np.ndarray, heading: np.ndarray, segments: np.ndarray) -> dict[str, np.ndarray]:
    """Nearest-lane queries, the reference for the simulator's lane kernels.

    The nearest lane centreline segment (point-to-segment distance) within
    :data:`LANE_SEARCH_RADIUS` is the agent's lane. The step is aligned when the
    heading error to that segment's direction is below :data:`ALIGN_MAX_HEADING_ERROR_DEG`.

    Args:
        xy: (..., 2) positions, m. heading: (...,) rad. segments: (S, 4) from :func:`lane_segments`.
    Returns:
        dict of (...,) arrays: ``lateral_offset`` (m, the true distance to the nearest
        lane centreline, near or not; :data:`NO_LANE_DISTANCE` when there is no lane),
        ``aligned`` (bool), ``segment`` (int64, -1 when none within the search radius).
    """
    xy = _as_float(xy, "xy")
    heading = _as_float(heading, "heading")
    seg = np.asarray(segments, np.float64).reshape(-1, 4)
    lead = heading.shape
    if seg.shape[0] == 0:
        return {"lateral_offset": np.full(lead, NO_LANE_DISTANCE), "aligned": np.zeros(lead, bool),
                "segment": np.full(lead, -1, np.int64)}
    p = xy[..., None, :]  # (..., 1, 2)
    a, b = seg[:, :2], seg[:, 2:]
    ab = b - a
    ab2 = np.maximum((ab * ab).sum(-1), 1e-12)
    t = np.clip(((p - a) * ab).sum(-1) / ab2, 0.0, 1.0)  # (..., S)
    closest = a + t[..., None] * ab
    dist = np.linalg.norm(p - closest, axis=-1)  # (..., S)
    nearest = np.argmin(dist, axis=-1)
    d = np.take_along_axis(dist, nearest[..., None], axis=-1)[..., 0]
    near = d <= LANE_SEARCH_RADIUS
    seg_heading = np.arctan2(ab[:, 1], ab[:, 0])[nearest]
    err = np.abs(wrap_angle(heading - seg_heading))
    aligned = near & (err < np.deg2rad(ALIGN_MAX_HEADING_ERROR_DEG))
    return {
        "lateral_offset": d,
        "aligned": aligned,
        "segment": np.where(near, nearest, -1),
    }


# ----------------------------------------------------------------------------- outcome classes
def outcome_class(
    goal: np.ndarray,
    at_fault_collision: np.ndarray,
    non_at_fault_collision: np.ndarray,
    offroad: np.ndarray,
) -> np.ndarray:
    """Outcome class per task, :class:`OutcomeClass` codes (int8).

    Priority: at-fault collision > off-road > completed > non-at-fault collision > timeout
    (a task with none of the four events timed out).
    """
    goal, af, nf, off = (_as_bool(v) for v in (goal, at_fault_collision, non_at_fault_collision, offroad))
    return np.select(
        [af, off, goal, nf],
        [OutcomeClass.AT_FAULT_COLLISION, OutcomeClass.OFFROAD, OutcomeClass.COMPLETED,
         OutcomeClass.NON_AT_FAULT_COLLISION],
        default=OutcomeClass.TIMEOUT,
    ).astype(np.int8)


def repaired(goal: np.ndarray, at_fault_collision: np.ndarray, non_at_fault_collision: np.ndarray,
             offroad: np.ndarray) -> np.ndarray:
    """The seed paper's repair (Table III): the ego reaches its goal without any collision
    (at fault or not) or off-road event. Co-player harm is not part of it (it is reported
    in its own column, see :func:`repair_table`)."""
    return (_as_bool(goal) & ~_as_bool(at_fault_collision) & ~_as_bool(non_at_fault_collision)
            & ~_as_bool(offroad))


def repair_table(reference_class: np.ndarray, other_clean: np.ndarray,
                 other_harm: np.ndarray | None = None) -> dict[str, dict[str, float]]:
    """Failure-repair analysis: for each outcome class of the reference policy, the number
    of task-regimes in it and the share that another policy repairs.

    Args:
        reference_class: (n,) :class:`OutcomeClass` codes of the reference policy.
        other_clean: (n,) bool, the other policy repaired the same task-regime
            (:func:`repaired`).
        other_harm: (n,) co-player harm of the other policy (other vehicles that collided
            or went off-road); optional, reported apart from the repair.
    Returns:
        ``{class_name: {"count": int, "share": fraction of all n, "repaired": fraction of
        that class the other policy repairs (nan when the class is empty)}}``, plus, with
        ``other_harm``, ``"harm"``: the fraction of that class in which the other policy
        harmed at least one co-player (nan when empty).
    """
    ref = np.asarray(reference_class).reshape(-1)
    ok = _as_bool(other_clean).reshape(-1)
    if ref.shape != ok.shape:
        raise ValueError(f"reference_class {ref.shape} and other_clean {ok.shape} differ in shape")
    harm = None if other_harm is None else np.asarray(other_harm).reshape(-1) > 0
    if harm is not None and harm.shape != ref.shape:
        raise ValueError(f"reference_class {ref.shape} and other_harm {harm.shape} differ in shape")
    n = max(ref.size, 1)
    out: dict[str, dict[str, float]] = {}
    for cls in OutcomeClass:
        m = ref == cls
        cnt = int(m.sum())
        out[cls.name.lower()] = {
            "count": cnt,
            "share": cnt / n,
            "repaired": float(ok[m].mean()) if cnt else float("nan"),
        }
        if harm is not None:
            out[cls.name.lower()]["harm"] = float(harm[m].mean()) if cnt else float("nan")
    return out


# ----------------------------------------------------------------------------- geometry (figures)
def box_corners(xy: np.ndarray, heading: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Corners of oriented boxes: (..., 4, 2) in the order front-left, front-right,
    rear-right, rear-left. ``size`` is (..., 2) = (length, width), m."""
    xy = np.asarray(xy, np.float64)
    h = np.asarray(heading, np.float64)
    size = np.asarray(size, np.float64)
    fwd = np.stack([np.cos(h), np.sin(h)], -1)
    left = np.stack([-np.sin(h), np.cos(h)], -1)
    hl = 0.5 * size[..., 0:1]
    hw = 0.5 * size[..., 1:2]
    signs = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], np.float64)  # (fwd, left) per corner
    return (xy[..., None, :] + signs[:, 0, None] * (hl * fwd)[..., None, :]
            + signs[:, 1, None] * (hw * left)[..., None, :])


# ----------------------------------------------------------------------------- aggregation
def rate(mask: np.ndarray) -> float:
    """Mean of a boolean array (nan when empty)."""
    m = np.asarray(mask)
    return float(m.mean()) if m.size else float("nan")


def summarize(per_task: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Aggregate one group of task results (one policy, regime and split).

    Args:
        per_task: arrays (n,) with keys ``score``, ``goal``, ``at_fault_collision``,
            ``offroad``, and optionally ``non_at_fault_collision``, ``timeout``,
            ``co_player_harm``, ``comfort``, ``lane_align``, ``lane_center``.
    Returns:
        ``score`` (mean, 0-100), ``completion``, ``at_fault_collision``, ``offroad``
        rates (fractions), and the optional means; ``n`` the number of tasks.
    """
    n = int(np.asarray(per_task["score"]).size)
    out: dict[str, float] = {
        "n": n,
        "score": float(np.mean(per_task["score"])) if n else float("nan"),
        "completion": rate(per_task["goal"]),
        "at_fault_collision": rate(per_task["at_fault_collision"]),
        "offroad": rate(per_task["offroad"]),
    }
    for key in ("non_at_fault_collision", "timeout"):
        if key in per_task:
            out[key] = rate(per_task[key])
    for key in ("co_player_harm", "comfort", "lane_align", "lane_center"):
        if key in per_task:
            v = np.asarray(per_task[key], np.float64)
            out[key] = float(v.mean()) if v.size else float("nan")
    return out
