"""BehaviorBench-style per-task metrics, pure NumPy and vectorised over tasks.

Definitions (``../shared/DESIGN.md``, Evaluation; the seed paper's weights):

* ``T`` = steps the ego was alive (decisions taken before it was removed or the episode ended).
* comfort = 1 - min(violations / (3 T), 1), where every step adds
  1{|a_long| > 3 m/s^2} + 1{|a_lat| > 3 m/s^2} + 1{|jerk| > 5 m/s^3}.
* lane_align = aligned steps / T; a step is aligned when a lane centreline lies within
  4 m and the heading error to it is below 15 degrees.
* lane_center = 1 - min(mean lateral distance / 2 m, 1); the lateral distance is the
  point-to-segment distance to the nearest lane centreline (10 m when none is within 4 m).
* score = 0 when the ego misses its goal, has an at-fault collision or goes off-road;
  otherwise 100 * (0.2 comfort + 0.5 lane_align + 0.3 lane_center).

At-fault classification follows nuPlan's five collision cases (``no_ego_at_fault_collisions``):
stopped ego (no fault), stopped other agent (fault), active rear (no fault), active front
(fault), active lateral (fault only while the ego spans two lanes).

Every function takes arrays with arbitrary leading "task" dimensions and works on all
of them at once; nothing loops over tasks in Python.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Mapping

import numpy as np

# ----------------------------------------------------------------------------- constants
#: Comfort thresholds: |a_long| (m/s^2), |a_lat| (m/s^2), |jerk| (m/s^3).
COMFORT_A_LONG_LIMIT = 3.0
COMFORT_A_LAT_LIMIT = 3.0
COMFORT_JERK_LIMIT = 5.0
#: Number of comfort checks per step (the 3 in 3 T).
COMFORT_CHECKS_PER_STEP = 3
#: Lane queries: search radius (m), alignment tolerance (deg), offset when no lane is near (m).
LANE_SEARCH_RADIUS = 4.0
ALIGN_MAX_HEADING_ERROR_DEG = 15.0
NO_LANE_OFFSET = 10.0
#: Mean lateral distance (m) at which lane_center reaches 0.
LANE_CENTER_CLAMP = 2.0
#: Score weights (comfort, lane_align, lane_center), the seed paper's.
SCORE_WEIGHTS = (0.2, 0.5, 0.3)
#: nuPlan's stopped-speed threshold (m/s).
STOPPED_SPEED_THRESHOLD = 5e-2
#: nuPlan's "agent behind" angle: relative bearing above this is behind (deg).
BEHIND_ANGLE_DEG = 150.0


class CollisionType(IntEnum):
    """nuPlan's collision cases, in the order they are tested."""

    STOPPED_EGO = 0
    STOPPED_TRACK = 1
    ACTIVE_REAR = 2
    ACTIVE_FRONT = 3
    ACTIVE_LATERAL = 4


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
def comfort_violations(a_long: np.ndarray, a_lat: np.ndarray, jerk: np.ndarray) -> np.ndarray:
    """Violations per step (0..3): 1{|a_long|>3} + 1{|a_lat|>3} + 1{|jerk|>5}.

    Args:
        a_long, a_lat: (...,) longitudinal / lateral acceleration, m/s^2.
        jerk: (...,) longitudinal jerk, m/s^3.
    Returns:
        (...,) int32 count of violated comfort limits.
    """
    a_long = _as_float(a_long, "a_long")
    a_lat = _as_float(a_lat, "a_lat")
    jerk = _as_float(jerk, "jerk")
    return (
        (np.abs(a_long) > COMFORT_A_LONG_LIMIT).astype(np.int32)
        + (np.abs(a_lat) > COMFORT_A_LAT_LIMIT).astype(np.int32)
        + (np.abs(jerk) > COMFORT_JERK_LIMIT).astype(np.int32)
    )


# ----------------------------------------------------------------------------- from accumulators
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


# ----------------------------------------------------------------------------- from trajectories
def metrics_from_steps(
    alive: np.ndarray,
    a_long: np.ndarray,
    a_lat: np.ndarray,
    jerk: np.ndarray,
    aligned: np.ndarray,
    lateral_offset: np.ndarray,
) -> dict[str, np.ndarray]:
    """Comfort, lane alignment and lane centring from per-step signals.

    Args (all (..., T); steps where ``alive`` is False are ignored):
        alive: bool, the ego existed at that step.
        a_long, a_lat: m/s^2. jerk: m/s^3.
        aligned: bool, lane-aligned at that step.
        lateral_offset: m, distance to the nearest lane centreline.
    Returns:
        The same dict as :func:`metrics_from_accumulators`, plus the accumulators
        themselves (``steps_alive``, ``comfort_violations``, ``aligned_steps``,
        ``lateral_offset_sum``) so both paths can be compared.
    """
    alive = _as_bool(alive)
    viol = np.where(alive, comfort_violations(a_long, a_lat, jerk), 0)
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
        m/s^3). Step 0 uses the first available difference (backward differences
        elsewhere), so a constant-acceleration trajectory gives a constant ``a_long``.
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
    return {"speed": speed, "a_long": a_long, "a_lat": a_lat, "jerk": jerk}


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
        dict of (...,) arrays: ``lateral_offset`` (m, :data:`NO_LANE_OFFSET` when no lane
        is near), ``aligned`` (bool), ``segment`` (int64, -1 when none).
    """
    xy = _as_float(xy, "xy")
    heading = _as_float(heading, "heading")
    seg = np.asarray(segments, np.float64).reshape(-1, 4)
    lead = heading.shape
    if seg.shape[0] == 0:
        return {"lateral_offset": np.full(lead, NO_LANE_OFFSET), "aligned": np.zeros(lead, bool),
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
        "lateral_offset": np.where(near, d, NO_LANE_OFFSET),
        "aligned": aligned,
        "segment": np.where(near, nearest, -1),
    }


# ----------------------------------------------------------------------------- score
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
    c, a, l = (_as_float(v, n) for v, n in ((comfort, "comfort"), (lane_align, "lane_align"),
                                             (lane_center, "lane_center")))
    for v, n in ((c, "comfort"), (a, "lane_align"), (l, "lane_center")):
        if np.any((v < -1e-9) | (v > 1 + 1e-9)):
            raise ValueError(f"{n}: values must lie in [0, 1]")
    success = _as_bool(goal) & ~_as_bool(at_fault_collision) & ~_as_bool(offroad)
    return np.where(success, 100.0 * (wc * c + wa * a + wl * l), 0.0)


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


def clean_completion(goal: np.ndarray, at_fault_collision: np.ndarray, offroad: np.ndarray,
                     co_player_harm: np.ndarray | None = None) -> np.ndarray:
    """Completed cleanly: reached the goal, no at-fault collision, no off-road and (when
    given) no other vehicle harmed."""
    ok = _as_bool(goal) & ~_as_bool(at_fault_collision) & ~_as_bool(offroad)
    if co_player_harm is not None:
        ok &= np.asarray(co_player_harm) == 0
    return ok


def repair_table(reference_class: np.ndarray, other_clean: np.ndarray) -> dict[str, dict[str, float]]:
    """Failure-repair analysis: for each outcome class of the reference policy, the number
    of task-regimes in it and the share that another policy completes cleanly.

    Args:
        reference_class: (n,) :class:`OutcomeClass` codes of the reference policy.
        other_clean: (n,) bool, the other policy completed the same task-regime cleanly.
    Returns:
        ``{class_name: {"count": int, "share": fraction of all n, "repaired": fraction of
        that class the other policy completes cleanly (nan when the class is empty)}}``.
    """
    ref = np.asarray(reference_class).reshape(-1)
    ok = _as_bool(other_clean).reshape(-1)
    if ref.shape != ok.shape:
        raise ValueError(f"reference_class {ref.shape} and other_clean {ok.shape} differ in shape")
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
    return out


# ----------------------------------------------------------------------------- at fault
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


def _segment_hits_box(p0: np.ndarray, p1: np.ndarray, xy: np.ndarray, heading: np.ndarray,
                      size: np.ndarray) -> np.ndarray:
    """Whether segment p0-p1 (..., 2) intersects the oriented box (Liang-Barsky in the box frame)."""
    c, s = np.cos(heading), np.sin(heading)

    def to_local(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = p - xy
        return d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c

    x0, y0 = to_local(p0)
    x1, y1 = to_local(p1)
    hl, hw = 0.5 * size[..., 0], 0.5 * size[..., 1]
    t_lo = np.zeros_like(x0)
    t_hi = np.ones_like(x0)
    hit = np.ones(x0.shape, bool)
    for start, delta, half in ((x0, x1 - x0, hl), (y0, y1 - y0, hw)):
        parallel = np.abs(delta) < 1e-12
        hit &= ~(parallel & (np.abs(start) > half))
        safe = np.where(parallel, 1.0, delta)
        ta = (-half - start) / safe
        tb = (half - start) / safe
        t_lo = np.where(parallel, t_lo, np.maximum(t_lo, np.minimum(ta, tb)))
        t_hi = np.where(parallel, t_hi, np.minimum(t_hi, np.maximum(ta, tb)))
    return hit & (t_lo <= t_hi)


def collision_type(
    ego_xy: np.ndarray, ego_heading: np.ndarray, ego_speed: np.ndarray, ego_size: np.ndarray,
    other_xy: np.ndarray, other_heading: np.ndarray, other_speed: np.ndarray, other_size: np.ndarray,
) -> np.ndarray:
    """nuPlan collision case per collision, :class:`CollisionType` codes (int8).

    Tested in nuPlan's order: ego stopped (speed <= 0.05 m/s); other agent stopped;
    other agent behind (bearing of its centre from the ego heading > 150 deg); the ego's
    front edge touches the other box (front); else lateral.

    Args: positions (..., 2) m, headings (...,) rad, speeds (...,) m/s (magnitudes are
    used), sizes (..., 2) = (length, width) m, all taken at the collision step.
    """
    ego_xy, other_xy = np.asarray(ego_xy, np.float64), np.asarray(other_xy, np.float64)
    eh, oh = np.asarray(ego_heading, np.float64), np.asarray(other_heading, np.float64)
    ego_size, other_size = np.asarray(ego_size, np.float64), np.asarray(other_size, np.float64)
    ego_stopped = np.abs(np.asarray(ego_speed, np.float64)) <= STOPPED_SPEED_THRESHOLD
    other_stopped = np.abs(np.asarray(other_speed, np.float64)) <= STOPPED_SPEED_THRESHOLD
    rel = other_xy - ego_xy
    norm = np.linalg.norm(rel, axis=-1)
    cos_bearing = np.where(
        norm > 1e-9,
        (rel[..., 0] * np.cos(eh) + rel[..., 1] * np.sin(eh)) / np.maximum(norm, 1e-9),
        1.0,  # coincident centres: treat as ahead
    )
    behind = np.arccos(np.clip(cos_bearing, -1.0, 1.0)) > np.deg2rad(BEHIND_ANGLE_DEG)
    corners = box_corners(ego_xy, eh, ego_size)
    front = _segment_hits_box(corners[..., 0, :], corners[..., 1, :], other_xy, oh, other_size)
    return np.select(
        [ego_stopped, other_stopped, behind, front],
        [CollisionType.STOPPED_EGO, CollisionType.STOPPED_TRACK, CollisionType.ACTIVE_REAR,
         CollisionType.ACTIVE_FRONT],
        default=CollisionType.ACTIVE_LATERAL,
    ).astype(np.int8)


def at_fault(collision_kind: np.ndarray, ego_spans_two_lanes: np.ndarray) -> np.ndarray:
    """nuPlan's fault rule for the ego: stopped other agent and front collisions are at
    fault; lateral collisions are at fault while the ego spans two lanes; a stopped ego
    and being rear-ended are not."""
    k = np.asarray(collision_kind)
    return (
        (k == CollisionType.STOPPED_TRACK)
        | (k == CollisionType.ACTIVE_FRONT)
        | ((k == CollisionType.ACTIVE_LATERAL) & _as_bool(ego_spans_two_lanes))
    )


def ego_spans_two_lanes(ego_xy: np.ndarray, ego_heading: np.ndarray, ego_size: np.ndarray,
                        segments: np.ndarray, lane_ids: np.ndarray) -> np.ndarray:
    """Whether the ego box straddles two lanes: its four corners do not all map to the
    same lane polyline (nearest lane centreline within the search radius, per corner).

    Corners with no lane within :data:`LANE_SEARCH_RADIUS` are ignored.
    Args: ego_xy (..., 2), ego_heading (...,), ego_size (..., 2), segments (S, 4),
    lane_ids (S,). Returns (...,) bool.
    """
    corners = box_corners(ego_xy, ego_heading, ego_size)  # (..., 4, 2)
    h = np.broadcast_to(np.asarray(ego_heading, np.float64)[..., None], corners.shape[:-1])
    q = lane_queries(corners, h, segments)
    ids = np.where(q["segment"] >= 0, np.asarray(lane_ids)[np.maximum(q["segment"], 0)], -1)
    valid = ids >= 0
    big = np.iinfo(np.int64).max
    lo = np.where(valid, ids, big).min(-1)
    hi = np.where(valid, ids, -1).max(-1)
    return valid.any(-1) & (lo != hi)


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
