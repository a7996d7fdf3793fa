"""BehaviorBench-style task splits: the interactivity score, Interactive-N and Random-N.

A *task* is one scenario with its designated ego (``Scenario.ego_index``). On WOMD there
is one task per ``tracks_to_predict`` vehicle (:func:`track_tasks`): the same scene with
``ego_index`` set to that vehicle, the scenario id unchanged. :func:`interactive_split`
and :func:`random_split` take either a list of tasks (used as given) or a folder of WOMD
files (``.json``, ``.json.gz``, ``.npz``), which they load and expand with
:func:`track_tasks` first.

The split builders only read :func:`interactivity_report` (eligibility and score per
task); the score below can be replaced without touching them.

The interactivity score of a task (one scenario, its designated ego) is

    S = 0.20 min(n_far_goal / 15, 1) + 0.25 min(mean |jerk| / 30, 1)
      + 0.15 min(mean |steer rate| / 2, 1) + 0.20 min(mean neighbours / 3, 1)
      + 0.20 min((ego goal distance - 10) / 40, 1)

in [0, 1]. Tasks whose ego goal is closer than 10 m, whose ego is not valid at t0, or
with fewer than 5 agents valid at t0 are *ineligible*: their score is ``None``, not 0.
Each term is computed from the logged data as documented in :func:`interactivity_terms`.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any, Sequence, Union

import numpy as np

from cpsim.scenario.datatypes import DT, AgentType, Scenario

__all__ = [
    "InteractivityTerms",
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
# Term definitions.
FAR_GOAL_DISTANCE = 10.0  # m, an agent "has a goal >= 10 m" away from its t0 position
NEIGHBOUR_RADIUS = 10.0  # m, centre-to-centre distance to the ego
#: Below this mean speed (m/s) over a step, steering is undefined (heading noise at standstill).
MIN_STEER_SPEED = 1.0
#: Wheelbase as a fraction of the box length (the jerk model's convention, DESIGN.md).
WHEELBASE_FRACTION = 0.6
#: Agent types whose kinematics (jerk, steering) enter the score: wheeled road users.
WHEELED_TYPES = (AgentType.VEHICLE, AgentType.CYCLIST)
# (weight, normaliser) per term, in the order of the formula above.
WEIGHTS = {
    "far_goal": (0.20, 15.0),
    "jerk": (0.25, 30.0),
    "steer": (0.15, 2.0),
    "neighbours": (0.20, 3.0),
    "ego_goal": (0.20, 40.0),
}


@dataclasses.dataclass(frozen=True)
class InteractivityTerms:
    """The raw terms of one task's interactivity score (for reports and tests).

    Attributes:
        scenario_id: the scenario's id.
        eligible: whether the task passes BehaviorBench's preconditions.
        reason: why it is ineligible ("" when eligible).
        agents_valid_t0: number of agents valid at t0 (ego included).
        agents_far_goal: agents valid at t0 whose goal is >= 10 m from their t0 position.
        mean_abs_jerk: mean |jerk| of wheeled agents over the logs, m/s^3.
        mean_abs_steer_rate: mean |steering-angle rate| of wheeled agents, rad/s.
        mean_neighbours: mean number of other agents within 10 m of the ego, per valid ego step.
        ego_goal_distance: ego's t0-to-goal distance, m (inf when the ego is invalid at t0).
        score: the interactivity score in [0, 1], or None when ineligible.
    """

    scenario_id: str
    eligible: bool
    reason: str
    agents_valid_t0: int
    agents_far_goal: int
    mean_abs_jerk: float
    mean_abs_steer_rate: float
    mean_neighbours: float
    ego_goal_distance: float
    score: float | None

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _masked_mean(values: np.ndarray, mask: np.ndarray) -> float:
    """Mean of ``values[mask]``; 0.0 when the mask is empty (no evidence of interaction)."""
    count = int(mask.sum())
    return float(values[mask].sum() / count) if count else 0.0


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Wrap radians to [-pi, pi)."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def _kinematic_terms(scenario: Scenario) -> tuple[float, float]:
    """(mean |jerk| in m/s^3, mean |steering rate| in rad/s) over wheeled agents' logs."""
    valid = scenario.log_valid
    wheeled = np.isin(scenario.agent_types, np.array(WHEELED_TYPES, np.int8))[:, None]
    speed = np.linalg.norm(scenario.log_velocity.astype(np.float64), axis=-1)  # (N, T)
    heading = scenario.log_heading.astype(np.float64)
    pair = valid[:, :-1] & valid[:, 1:]  # (N, T-1): step t -> t+1 exists
    # Longitudinal acceleration a_t = (v_{t+1} - v_t) / dt, jerk j_t = (a_{t+1} - a_t) / dt.
    accel = np.where(pair, np.diff(speed, axis=1) / DT, 0.0)
    jerk = np.diff(accel, axis=1) / DT  # (N, T-2)
    jerk_mask = pair[:, :-1] & pair[:, 1:] & wheeled
    # Steering angle from the kinematic bicycle model: yaw_rate = v tan(delta) / wheelbase,
    # so delta_t = atan(wheelbase * yaw_rate_t / v_t) with yaw_rate_t = wrap(h_{t+1} - h_t) / dt
    # and v_t the mean logged speed over the step; undefined (masked) below MIN_STEER_SPEED.
    mean_speed = 0.5 * (speed[:, :-1] + speed[:, 1:])
    steer_ok = pair & (mean_speed >= MIN_STEER_SPEED)
    yaw_rate = _wrap(np.diff(heading, axis=1)) / DT
    wheelbase = WHEELBASE_FRACTION * scenario.sizes[:, :1].astype(np.float64)  # (N, 1)
    steer = np.where(steer_ok, np.arctan(wheelbase * yaw_rate / np.where(steer_ok, mean_speed, 1.0)), 0.0)
    steer_rate = np.diff(steer, axis=1) / DT  # (N, T-2)
    steer_mask = steer_ok[:, :-1] & steer_ok[:, 1:] & wheeled
    return _masked_mean(np.abs(jerk), jerk_mask), _masked_mean(np.abs(steer_rate), steer_mask)


def interactivity_terms(scenario: Scenario) -> InteractivityTerms:
    """Compute every term of the interactivity score and the eligibility of a task.

    Definitions (``dt`` = 0.1 s, ``v`` = norm of ``log_velocity``, all in float64):

    * eligibility: the ego is valid at t0, its goal is >= 10 m from its t0 position, and
      at least 5 agents (ego included, any type) are valid at t0.
    * ``agents_far_goal``: agents (any type, ego included) valid at t0 whose goal is >= 10 m
      from their t0 position.
    * ``mean_abs_jerk``: over wheeled agents (vehicles, cyclists) and every t with steps
      t, t+1, t+2 valid: ``|a_{t+1} - a_t| / dt`` with ``a_t = (v_{t+1} - v_t) / dt``.
    * ``mean_abs_steer_rate``: over wheeled agents and every t with steps t..t+2 valid and a
      mean speed >= 1 m/s on both steps: ``|delta_{t+1} - delta_t| / dt`` with
      ``delta_t = atan(0.6 length * wrap(h_{t+1} - h_t) / dt / vbar_t)``,
      ``vbar_t = (v_t + v_{t+1}) / 2`` (kinematic bicycle, wheelbase 0.6 x length).
    * ``mean_neighbours``: over the ego's valid steps, the number of other agents valid at
      that step whose centre is within 10 m (<=) of the ego's centre.
    * ``ego_goal_distance``: ``|goal - xy_t0|`` of the ego.

    An empty set of samples gives a term of 0.
    """
    ego = scenario.ego_index
    valid = scenario.log_valid
    xy = scenario.log_xy.astype(np.float64)
    valid_t0 = valid[:, 0]
    goal_dist = np.linalg.norm(scenario.goal_xy.astype(np.float64) - xy[:, 0], axis=-1)
    agents_valid_t0 = int(valid_t0.sum())
    far_goal = int((valid_t0 & (goal_dist >= FAR_GOAL_DISTANCE)).sum())
    ego_goal = float(goal_dist[ego]) if valid_t0[ego] else float("inf")

    ego_valid = valid[ego]  # (T,)
    dist = np.linalg.norm(xy - xy[ego][None], axis=-1)  # (N, T)
    near = valid & ego_valid[None] & (dist <= NEIGHBOUR_RADIUS)
    near[ego] = False
    steps = int(ego_valid.sum())
    mean_neighbours = float(near.sum() / steps) if steps else 0.0
    mean_jerk, mean_steer = _kinematic_terms(scenario)

    if not valid_t0[ego]:
        reason = "ego is not valid at t0"
    elif ego_goal < MIN_EGO_GOAL_DISTANCE:
        reason = f"ego goal {ego_goal:.2f} m away (< {MIN_EGO_GOAL_DISTANCE:g} m)"
    elif agents_valid_t0 < MIN_AGENTS_AT_T0:
        reason = f"{agents_valid_t0} agents valid at t0 (< {MIN_AGENTS_AT_T0})"
    else:
        reason = ""
    score = None
    if not reason:
        raw = {
            "far_goal": far_goal,
            "jerk": mean_jerk,
            "steer": mean_steer,
            "neighbours": mean_neighbours,
            "ego_goal": ego_goal - MIN_EGO_GOAL_DISTANCE,
        }
        score = float(sum(w * min(raw[k] / norm, 1.0) for k, (w, norm) in WEIGHTS.items()))
    return InteractivityTerms(
        scenario_id=scenario.id,
        eligible=not reason,
        reason=reason,
        agents_valid_t0=agents_valid_t0,
        agents_far_goal=far_goal,
        mean_abs_jerk=mean_jerk,
        mean_abs_steer_rate=mean_steer,
        mean_neighbours=mean_neighbours,
        ego_goal_distance=ego_goal,
        score=score,
    )


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
    for i, s in enumerate(scenarios):
        if not isinstance(s, Scenario):
            raise ValueError(f"scenarios[{i}]: expected a Scenario, got {type(s).__name__}")
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
    pool = list(scenarios)
    if not pool:
        raise ValueError("scenarios: empty; a split needs at least one scenario")
    for i, s in enumerate(pool):
        if not isinstance(s, Scenario):
            raise ValueError(f"scenarios[{i}]: expected a Scenario, got {type(s).__name__}")
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
