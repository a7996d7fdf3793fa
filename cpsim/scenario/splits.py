"""BehaviorBench task splits: the interactivity score, Interactive-N and Random-N.

A *task* is one scenario with its designated ego (``Scenario.ego_index``). On WOMD there
is one task per ``tracks_to_predict`` vehicle (:func:`track_tasks`): the same scene with
``ego_index`` set to that vehicle, the scenario id unchanged. :func:`interactive_split`
and :func:`random_split` take either a list of tasks (used as given) or a folder of WOMD
files (``.json``, ``.json.gz``, ``.npz``), which they load and expand with
:func:`track_tasks` first.

The split builders only read :func:`interactivity_report` (eligibility and score per
task).

The interactivity score of a task is BehaviorBench's (``../shared/DESIGN.md``, section
"Evaluation"): a weighted sum of eight capped terms, each ``min(x / cap, 1)``, times a
lane multiplier::

    S = lane_mult x ( 0.10 min(agents within 50 m at t0 / 15, 1)
                    + 0.10 min(mean summed |d accel| / 30, 1)
                    + 0.05 min(mean steering change / 2, 1)
                    + 0.10 min(mean agents within 10 m / 3, 1)
                    + 0.15 min((ego goal distance - 10 m) / 40, 1)
                    + 0.25 min(agents whose path crosses the ego's within 5 m / 5, 1)
                    + 0.20 min(steps with a time-to-collision < 3 s / 20, 1)
                    + 0.05 min(|ego heading change| / (pi / 2), 1) )

with ``lane_mult = 1.0`` when the ego's goal is off its current lane chain (300 m ahead,
5 m tolerance) and 0.5 when it is on it. The weights sum to 1, so ``S`` is in [0, 1].
Tasks whose ego goal is closer than 10 m, whose ego is not valid at t0, or with fewer than
5 agents valid at t0 are *ineligible*: their score is ``None``, not 0. Each term is
computed from the logged data, vectorised over agents and steps, as documented in
:func:`interactivity_terms`.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any, Sequence, Union

import numpy as np

from cpsim.config import CLASSIC_ACCEL, CLASSIC_STEER
from cpsim.scenario.datatypes import DT, AgentType, RoadType, Scenario, validate_scenarios
from cpsim.scenario.geometry_utils import point_polyline_distance, point_segment_distance

__all__ = [
    "InteractivityTerms",
    "TERMS",
    "ego_lane_chain",
    "interactive_split",
    "interactivity_report",
    "interactivity_score",
    "interactivity_terms",
    "random_split",
    "track_tasks",
]

#: What the split builders accept: a list of tasks, or a folder of WOMD files.
TaskSource = Union[str, "os.PathLike[str]", Sequence[Scenario]]

# Eligibility (BehaviorBench).
MIN_EGO_GOAL_DISTANCE = 10.0  # m
MIN_AGENTS_AT_T0 = 5
# Term definitions (BehaviorBench).
NEAR_T0_RADIUS = 50.0  # m, "agents within 50 m at t0" (centre to centre)
NEIGHBOUR_RADIUS = 10.0  # m, "mean agents within 10 m"
PATH_CROSS_RADIUS = 5.0  # m, two logged paths "cross" when they come this close
TTC_THRESHOLD = 3.0  # s
TTC_RADIUS = 50.0  # m, only agents this close to the ego enter the time-to-collision test
MIN_CLOSING_SPEED = 0.1  # m/s, below it the pair is not closing (no time-to-collision)
LANE_CHAIN_LENGTH = 300.0  # m of lane followed ahead of the ego
LANE_CHAIN_TOLERANCE = 5.0  # m: the ego's lane is within it at t0, the goal is "on" the chain within it
LANE_MULT_OFF_CHAIN = 1.0
LANE_MULT_ON_CHAIN = 0.5
# Our choices where BehaviorBench's description leaves a detail open (documented in interactivity_terms).
#: Largest heading difference between the ego and a lane segment for that lane to be the ego's.
LANE_HEADING_TOLERANCE = math.pi / 4
#: A lane continues another when its first vertex is this close to the other's last (WOMD lanes
#: share the junction vertex exactly).
LANE_LINK_DISTANCE = 0.5  # m
#: Below this mean speed (m/s) over a step, steering is undefined (heading noise at standstill).
MIN_STEER_SPEED = 1.0
#: Agent types whose inferred actions (acceleration, steering) enter the score: wheeled road users.
WHEELED_TYPES = (AgentType.VEHICLE, AgentType.CYCLIST)
#: Range of the inferred actions: the classic bicycle's action table (m/s^2, rad).
ACCEL_RANGE = (float(CLASSIC_ACCEL.min()), float(CLASSIC_ACCEL.max()))
STEER_RANGE = (float(CLASSIC_STEER.min()), float(CLASSIC_STEER.max()))

#: (name, weight, cap) of the eight terms, in the order of the formula; the name is the
#: :class:`InteractivityTerms` attribute holding the raw value (``ego_goal_distance`` enters
#: as ``distance - 10 m``).
TERMS: tuple[tuple[str, float, float], ...] = (
    ("agents_near_t0", 0.10, 15.0),
    ("mean_accel_change", 0.10, 30.0),
    ("mean_steer_change", 0.05, 2.0),
    ("mean_neighbours", 0.10, 3.0),
    ("ego_goal_distance", 0.15, 40.0),
    ("path_crossings", 0.25, 5.0),
    ("ttc_steps", 0.20, 20.0),
    ("ego_heading_change", 0.05, math.pi / 2),
)


@dataclasses.dataclass(frozen=True)
class InteractivityTerms:
    """The raw terms of one task's interactivity score (for reports and tests).

    Attributes:
        scenario_id: the scenario's id.
        ego_index: the task's ego.
        eligible: whether the task passes BehaviorBench's preconditions.
        reason: why it is ineligible ("" when eligible).
        agents_valid_t0: number of agents valid at t0 (ego included, any type).
        agents_near_t0: other agents valid at t0 within 50 m of the ego.
        mean_accel_change: mean over steps of the summed |change of inferred acceleration|
            of wheeled agents, m/s^2.
        mean_steer_change: mean |change of inferred steering angle| of wheeled agents, rad.
        mean_neighbours: mean number of other agents within 10 m of the ego, per valid ego step.
        ego_goal_distance: ego's t0-to-goal distance, m (inf when the ego is invalid at t0).
        path_crossings: other agents whose logged path comes within 5 m of the ego's.
        ttc_steps: ego steps with a time-to-collision below 3 s to some agent.
        ego_heading_change: |wrapped heading at the ego's last valid step - at t0|, rad.
        goal_on_lane_chain: whether the ego's goal is within 5 m of its lane chain.
        lane_mult: 0.5 when the goal is on the lane chain, else 1.0.
        score: the interactivity score in [0, 1], or None when ineligible.
    """

    scenario_id: str
    ego_index: int
    eligible: bool
    reason: str
    agents_valid_t0: int
    agents_near_t0: int
    mean_accel_change: float
    mean_steer_change: float
    mean_neighbours: float
    ego_goal_distance: float
    path_crossings: int
    ttc_steps: int
    ego_heading_change: float
    goal_on_lane_chain: bool
    lane_mult: float
    score: float | None

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def capped(self) -> dict[str, float]:
        """Each term's ``min(x / cap, 1)`` in [0, 1], by name (before weights and lane_mult)."""
        out = {}
        for name, _weight, cap in TERMS:
            x = getattr(self, name)
            if name == "ego_goal_distance":
                x = x - MIN_EGO_GOAL_DISTANCE
            out[name] = float(min(max(x, 0.0) / cap, 1.0))
        return out

    def contributions(self) -> dict[str, float]:
        """Each term's weighted share of the score (``lane_mult x weight x capped``)."""
        capped = self.capped()
        return {name: self.lane_mult * weight * capped[name] for name, weight, _cap in TERMS}


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Wrap radians to [-pi, pi)."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def _inferred_action_terms(scenario: Scenario) -> tuple[float, float]:
    """(mean summed |d accel| in m/s^2, mean |d steering| in rad) of wheeled agents' logs.

    The logged motion is read as classic-bicycle actions, clipped to the action table:
    ``a_t = clip((v_{t+1} - v_t) / dt, -4, 4)`` and
    ``delta_t = clip(atan(length x wrap(h_{t+1} - h_t) / dt / vbar_t), -1, 1)``.
    """
    valid = scenario.log_valid
    wheeled = np.isin(scenario.agent_types, np.array(WHEELED_TYPES, np.int8))[:, None]
    speed = np.linalg.norm(scenario.log_velocity.astype(np.float64), axis=-1)  # (N, T)
    heading = scenario.log_heading.astype(np.float64)
    pair = valid[:, :-1] & valid[:, 1:]  # (N, T-1): step t -> t+1 exists
    accel = np.clip(np.where(pair, np.diff(speed, axis=1) / DT, 0.0), *ACCEL_RANGE)
    accel_ok = pair[:, :-1] & pair[:, 1:] & wheeled  # (N, T-2)
    d_accel = np.where(accel_ok, np.abs(np.diff(accel, axis=1)), 0.0)
    steps = accel_ok.any(axis=0)  # steps with at least one sample
    mean_accel_change = float(d_accel.sum(axis=0)[steps].mean()) if steps.any() else 0.0

    mean_speed = 0.5 * (speed[:, :-1] + speed[:, 1:])
    steer_ok = pair & (mean_speed >= MIN_STEER_SPEED)
    yaw_rate = _wrap(np.diff(heading, axis=1)) / DT
    length = scenario.sizes[:, :1].astype(np.float64)  # (N, 1)
    steer = np.where(steer_ok, np.arctan(length * yaw_rate / np.where(steer_ok, mean_speed, 1.0)), 0.0)
    steer = np.clip(steer, *STEER_RANGE)
    steer_mask = steer_ok[:, :-1] & steer_ok[:, 1:] & wheeled
    count = int(steer_mask.sum())
    d_steer = np.abs(np.diff(steer, axis=1))
    mean_steer_change = float(d_steer[steer_mask].sum() / count) if count else 0.0
    return mean_accel_change, mean_steer_change


def _path_crossings(scenario: Scenario, ego: int) -> int:
    """Other agents whose logged positions come within 5 m of any logged ego position."""
    valid = scenario.log_valid
    xy = scenario.log_xy.astype(np.float64)
    ego_xy = xy[ego][valid[ego]]  # (Te, 2)
    if ego_xy.shape[0] == 0:
        return 0
    # Bounding-box prefilter per agent, then (N', T, Te) distances for the candidates only.
    lo, hi = ego_xy.min(axis=0) - PATH_CROSS_RADIUS, ego_xy.max(axis=0) + PATH_CROSS_RADIUS
    inside = valid & np.all((xy >= lo) & (xy <= hi), axis=-1)  # (N, T)
    inside[ego] = False
    rows = np.flatnonzero(inside.any(axis=1))
    if rows.size == 0:
        return 0
    d2 = ((xy[rows][:, :, None, :] - ego_xy[None, None]) ** 2).sum(-1)  # (N', T, Te)
    close = (d2 <= PATH_CROSS_RADIUS**2) & inside[rows][:, :, None]
    return int(close.any(axis=(1, 2)).sum())


def _ttc_steps(scenario: Scenario, ego: int) -> int:
    """Ego steps where some other agent within 50 m closes faster than 0.1 m/s with a
    time-to-collision (centre distance / closing speed) below 3 s."""
    valid = scenario.log_valid
    xy = scenario.log_xy.astype(np.float64)
    vel = scenario.log_velocity.astype(np.float64)
    rel = xy - xy[ego][None]  # (N, T, 2)
    rel_v = vel - vel[ego][None]
    dist = np.linalg.norm(rel, axis=-1)  # (N, T)
    ok = valid & valid[ego][None] & (dist <= TTC_RADIUS) & (dist > 0.0)
    ok[ego] = False
    closing = -np.einsum("ntk,ntk->nt", rel, rel_v) / np.where(ok, dist, 1.0)
    hit = ok & (closing > MIN_CLOSING_SPEED) & (dist < TTC_THRESHOLD * closing)
    return int(hit.any(axis=0).sum())


def _lane_segments(scenario: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Segments of every lane centreline: (start vertex index into ``road_points`` of each
    segment, the road it belongs to, the lanes (roads) with >= 2 vertices)."""
    offsets = scenario.road_offsets.astype(np.int64)
    counts = np.diff(offsets)
    lanes = np.flatnonzero((scenario.road_types == RoadType.LANE) & (counts >= 2))
    road_of = np.repeat(np.arange(scenario.num_roads), counts)  # (P,)
    start = np.flatnonzero(np.isin(road_of[:-1], lanes) & (road_of[:-1] == road_of[1:]))
    return start, road_of[start], lanes


def _truncate(polyline: np.ndarray, length: float) -> np.ndarray:
    """The first ``length`` metres of ``polyline`` (the last vertex interpolated)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(polyline, axis=0), axis=1))])
    if s[-1] <= length:
        return polyline
    k = int(np.searchsorted(s, length, side="right"))  # s[k-1] <= length < s[k]
    f = (length - s[k - 1]) / max(s[k] - s[k - 1], 1e-12)
    return np.concatenate([polyline[:k], polyline[k - 1] + f * (polyline[k:k + 1] - polyline[k - 1])])


def ego_lane_chain(scenario: Scenario, ego: int | None = None) -> np.ndarray | None:
    """(M, 2) polyline of the ego's current lane chain: the 300 m of lane ahead of it at t0.

    The ego's lane is the lane centreline segment nearest to its t0 position among those
    within 5 m whose direction is within 45 degrees of its t0 heading. The chain starts at the
    ego's projection on that segment, follows the lane to its end, then its continuation (a
    lane whose first vertex is within 0.5 m of the last one; the one whose first segment turns
    least when there are several, a lane never visited twice) until 300 m. ``None`` when
    the ego is invalid at t0 or no lane qualifies.
    """
    ego = scenario.ego_index if ego is None else int(ego)
    if not scenario.log_valid[ego, 0]:
        return None
    start, road_of, lanes = _lane_segments(scenario)
    if start.size == 0:
        return None
    pts = scenario.road_points.astype(np.float64)
    offsets = scenario.road_offsets.astype(np.int64)
    seg_a, seg_b = pts[start], pts[start + 1]
    p = scenario.log_xy[ego, 0].astype(np.float64)
    h = float(scenario.log_heading[ego, 0])
    d = point_segment_distance(p[None], seg_a, seg_b)[0]
    seg_dir = seg_b - seg_a
    seg_heading = np.arctan2(seg_dir[:, 1], seg_dir[:, 0])
    ok = (d <= LANE_CHAIN_TOLERANCE) & (np.abs(_wrap(seg_heading - h)) <= LANE_HEADING_TOLERANCE)
    if not ok.any():
        return None
    k = int(np.flatnonzero(ok)[np.argmin(d[ok])])
    ab = seg_dir[k]
    t = float(np.clip(np.dot(p - seg_a[k], ab) / max(np.dot(ab, ab), 1e-12), 0.0, 1.0))
    lane = int(road_of[k])
    pieces = [(seg_a[k] + t * ab)[None], pts[start[k] + 1:offsets[lane + 1]]]
    first = pts[offsets[lanes]]  # first vertex of every lane
    first_dir = pts[offsets[lanes] + 1] - first
    first_heading = np.arctan2(first_dir[:, 1], first_dir[:, 0])
    visited = {lane}
    length = float(np.linalg.norm(np.diff(np.concatenate(pieces), axis=0), axis=1).sum())
    while length < LANE_CHAIN_LENGTH:
        last, before = pts[offsets[lane + 1] - 1], pts[offsets[lane + 1] - 2]
        nxt = np.flatnonzero(np.linalg.norm(first - last, axis=1) <= LANE_LINK_DISTANCE)
        nxt = np.array([j for j in nxt if int(lanes[j]) not in visited], np.int64)
        if nxt.size == 0:
            break
        end_heading = math.atan2(last[1] - before[1], last[0] - before[0])
        j = int(nxt[np.argmin(np.abs(_wrap(first_heading[nxt] - end_heading)))])
        lane = int(lanes[j])
        visited.add(lane)
        piece = pts[offsets[lane]:offsets[lane + 1]]
        pieces.append(piece)
        length += float(np.linalg.norm(np.diff(piece, axis=0), axis=1).sum())
    chain = np.concatenate(pieces)
    if chain.shape[0] == 1:  # the ego projects onto a lane's last vertex
        chain = np.concatenate([chain, chain])
    return _truncate(chain, LANE_CHAIN_LENGTH)


def _goal_on_lane_chain(scenario: Scenario, ego: int) -> bool:
    chain = ego_lane_chain(scenario, ego)
    if chain is None:
        return False
    goal = scenario.goal_xy[ego].astype(np.float64)[None]
    return bool(point_polyline_distance(goal, chain)[0] <= LANE_CHAIN_TOLERANCE)


def interactivity_terms(scenario: Scenario) -> InteractivityTerms:
    """Compute every term of the interactivity score and the eligibility of a task.

    Definitions (``dt`` = 0.1 s, ``v`` = norm of ``log_velocity``, distances centre to
    centre, all in float64; "wheeled" = vehicles and cyclists):

    * eligibility: the ego is valid at t0, its goal is >= 10 m from its t0 position, and
      at least 5 agents (ego included, any type) are valid at t0.
    * ``agents_near_t0``: other agents (any type) valid at t0 within 50 m (<=) of the ego.
    * ``mean_accel_change``: the logs read as classic-bicycle actions, clipped to the action
      table: ``a_t = clip((v_{t+1} - v_t) / dt, -4, 4)``; at every t, the sum over wheeled
      agents with steps t..t+2 valid of ``|a_{t+1} - a_t|``; mean over the t with at least
      one such agent.
    * ``mean_steer_change``: ``delta_t = clip(atan(length x wrap(h_{t+1} - h_t) / dt /
      vbar_t), -1, 1)`` (classic bicycle, ``vbar_t = (v_t + v_{t+1}) / 2``, undefined below
      1 m/s); mean of ``|delta_{t+1} - delta_t|`` over wheeled agents and t where both exist.
    * ``mean_neighbours``: over the ego's valid steps, the number of other agents valid at
      that step within 10 m (<=) of the ego.
    * ``ego_goal_distance``: ``|goal - xy_t0|`` of the ego (the term uses it minus 10 m).
    * ``path_crossings``: other agents (any type) with some valid logged position within
      5 m (<=) of some valid logged ego position, at any two times.
    * ``ttc_steps``: ego-valid steps at which some other valid agent within 50 m (<=) has a
      closing speed ``-(dp . dv) / |dp|`` above 0.1 m/s and ``|dp| / closing < 3 s``.
    * ``ego_heading_change``: ``|wrap(h_last - h_t0)|`` over the ego's valid steps.
    * ``lane_mult``: 0.5 when the ego's goal is within 5 m of :func:`ego_lane_chain`, else
      1.0 (also when the ego has no lane at t0).

    An empty set of samples gives a term of 0.
    """
    ego = scenario.ego_index
    valid = scenario.log_valid
    xy = scenario.log_xy.astype(np.float64)
    valid_t0 = valid[:, 0]
    agents_valid_t0 = int(valid_t0.sum())
    ego_goal = (float(np.linalg.norm(scenario.goal_xy[ego].astype(np.float64) - xy[ego, 0]))
                if valid_t0[ego] else float("inf"))

    ego_valid = valid[ego]  # (T,)
    dist = np.linalg.norm(xy - xy[ego][None], axis=-1)  # (N, T)
    others = np.ones(scenario.num_agents, bool)
    others[ego] = False
    near_t0 = int((others & valid_t0 & valid_t0[ego] & (dist[:, 0] <= NEAR_T0_RADIUS)).sum())
    near = valid & ego_valid[None] & (dist <= NEIGHBOUR_RADIUS) & others[:, None]
    steps = int(ego_valid.sum())
    mean_neighbours = float(near.sum() / steps) if steps else 0.0
    mean_accel, mean_steer = _inferred_action_terms(scenario)
    ego_steps = np.flatnonzero(ego_valid)
    heading_change = (float(abs(_wrap(float(scenario.log_heading[ego, ego_steps[-1]])
                                      - float(scenario.log_heading[ego, ego_steps[0]]))))
                      if ego_steps.size else 0.0)
    on_chain = _goal_on_lane_chain(scenario, ego)

    if not valid_t0[ego]:
        reason = "ego is not valid at t0"
    elif ego_goal < MIN_EGO_GOAL_DISTANCE:
        reason = f"ego goal {ego_goal:.2f} m away (< {MIN_EGO_GOAL_DISTANCE:g} m)"
    elif agents_valid_t0 < MIN_AGENTS_AT_T0:
        reason = f"{agents_valid_t0} agents valid at t0 (< {MIN_AGENTS_AT_T0})"
    else:
        reason = ""
    terms = InteractivityTerms(
        scenario_id=scenario.id,
        ego_index=int(ego),
        eligible=not reason,
        reason=reason,
        agents_valid_t0=agents_valid_t0,
        agents_near_t0=near_t0,
        mean_accel_change=mean_accel,
        mean_steer_change=mean_steer,
        mean_neighbours=mean_neighbours,
        ego_goal_distance=ego_goal,
        path_crossings=_path_crossings(scenario, ego),
        ttc_steps=_ttc_steps(scenario, ego),
        ego_heading_change=heading_change,
        goal_on_lane_chain=on_chain,
        lane_mult=LANE_MULT_ON_CHAIN if on_chain else LANE_MULT_OFF_CHAIN,
        score=None,
    )
    if reason:
        return terms
    return dataclasses.replace(terms, score=float(sum(terms.contributions().values())))


def interactivity_score(scenario: Scenario) -> float | None:
    """BehaviorBench interactivity score in [0, 1], or None when the task is ineligible.

    See :func:`interactivity_terms` for the definition of every term.
    """
    return interactivity_terms(scenario).score


def interactivity_report(scenarios: Sequence[Scenario]) -> list[InteractivityTerms]:
    """Eligibility, reason, raw terms and score of every scenario, in input order."""
    return [interactivity_terms(s) for s in scenarios]


def track_tasks(scenarios: Sequence[Scenario], vehicles_only: bool = True) -> list[Scenario]:
    """One task per ``tracks_to_predict`` agent of each scenario (BehaviorBench on WOMD).

    Each task is the scenario with ``ego_index`` set to that agent (``dataclasses.replace``:
    arrays are shared, the id, source and everything else are unchanged), in scenario
    order, then ``tracks_to_predict`` order; repeated indices count once. With
    ``vehicles_only`` (the default, as in BehaviorBench) only vehicle tracks make tasks.
    A scenario without ``tracks_to_predict`` (procedural scenes, or a WOMD file that lists
    none) gives one task: itself, with its own ego (``sdc_track_index`` for WOMD); one whose
    tracks are all non-vehicles gives none. Eligibility is not checked here.
    """
    out: list[Scenario] = []
    for s in validate_scenarios(scenarios, single=False):
        tracks = [int(k) for k in dict.fromkeys(s.tracks_to_predict.tolist())]
        if not tracks:
            out.append(s)
            continue
        for k in tracks:
            if vehicles_only and s.agent_types[k] != AgentType.VEHICLE:
                continue
            out.append(s if k == s.ego_index else dataclasses.replace(s, ego_index=k))
    return out


def _is_folder_source(source: Any) -> bool:
    return isinstance(source, (str, os.PathLike))


def _tasks_of(source: TaskSource, cache_dir: str | os.PathLike | None) -> list[Scenario]:
    """A folder -> :func:`track_tasks` of its scenarios; a list -> the list itself."""
    if not _is_folder_source(source):
        if cache_dir is not None:
            raise ValueError("cache_dir: only used when the source is a folder")
        return list(source)
    from cpsim.scenario.womd import load_dir

    scenarios, _report = load_dir(source, cache_dir=cache_dir)  # skipped files are warned about
    return track_tasks(scenarios)


def _check_split_args(scenarios: Sequence[Scenario], n: Any) -> list[Scenario]:
    pool = validate_scenarios(scenarios, needs="a split", single=False)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"n: expected a non-negative integer, got {n!r}")
    return pool


def interactive_split(scenarios: TaskSource, n: int, *,
                      cache_dir: str | os.PathLike | None = None) -> list[Scenario]:
    """Interactive-N: the ``n`` eligible tasks with the highest interactivity score.

    ``scenarios`` is a list of tasks (scenarios, each with its ``ego_index``) or a folder
    of WOMD files, loaded with :func:`cpsim.scenario.load_dir` (``cache_dir`` passed on)
    and expanded to one task per ``tracks_to_predict`` vehicle (:func:`track_tasks`).
    Ordered by score (descending), ties broken by scenario id, then ego index, then input
    position, so the result is deterministic. Raises ``ValueError`` for an empty pool or
    when ``n`` exceeds the number of eligible tasks (``ScenarioError``, a ``ValueError``,
    for a folder without loadable scenarios).
    """
    pool = _check_split_args(_tasks_of(scenarios, cache_dir), n)
    report = interactivity_report(pool)
    ranked = [(-t.score, s.id, s.ego_index, i) for i, (s, t) in enumerate(zip(pool, report)) if t.eligible]
    if n > len(ranked):
        raise ValueError(f"n: {n} exceeds the {len(ranked)} eligible {_what(scenarios)} (of {len(pool)})")
    ranked.sort()
    return [pool[item[-1]] for item in ranked[:n]]


def _what(source: TaskSource) -> str:
    return "tasks" if _is_folder_source(source) else "scenarios"


def random_split(scenarios: TaskSource, n: int, seed: int, eligible_only: bool | None = None, *,
                 cache_dir: str | os.PathLike | None = None) -> list[Scenario]:
    """Random-N: ``n`` tasks drawn uniformly without replacement, seeded.

    ``scenarios``: a list of tasks or a folder of WOMD files (see :func:`interactive_split`).
    The draw is the first ``n`` entries of a seeded permutation (``numpy.random.default_rng``),
    so the same seed gives the same split and Random-n is a prefix of Random-m for n <= m.
    With ``eligible_only`` the draw is among tasks eligible for the interactivity score;
    its default (None) is True for a folder (BehaviorBench: eligible tasks only) and False
    for a list (unchanged behaviour). Raises ``ValueError`` for an empty pool or when ``n``
    exceeds the pool.
    """
    if eligible_only is None:
        eligible_only = _is_folder_source(scenarios)
    pool = _check_split_args(_tasks_of(scenarios, cache_dir), n)
    if eligible_only:
        pool = [s for s, t in zip(pool, interactivity_report(pool)) if t.eligible]
    if n > len(pool):
        what = f"eligible {_what(scenarios)}" if eligible_only else _what(scenarios)
        raise ValueError(f"n: {n} exceeds the {len(pool)} {what} available")
    order = np.random.default_rng(seed).permutation(len(pool))
    return [pool[int(i)] for i in order[:n]]
