"""Simulator configuration and the integer codes shared by kernels and front-ends.

:class:`SimConfig` is a frozen dataclass; :meth:`SimConfig.from_dict` rejects unknown
keys and ``__post_init__`` validates every field (``ValueError`` naming the field).
Numbers default to ``../shared/DESIGN.md`` (WOMD / GPUDrive / PufferDrive conventions).
"""

from __future__ import annotations

import dataclasses
from enum import IntEnum
from typing import Any, Mapping

import numpy as np


class Controller(IntEnum):
    """Who drives an agent slot."""

    POLICY = 0  #: actions come from ``Simulator.step``
    REPLAY = 1  #: follows its log; disappears when its log becomes invalid
    IDM = 2     #: IDM speed control along its logged path, yields to crossing agents
    STATIC = 3  #: stays where it is with speed 0
    NONE = 4    #: empty slot


class Outcome(IntEnum):
    """Per-agent episode outcome; sticky after the first event."""

    RUNNING = 0
    GOAL = 1
    COLLISION = 2
    OFFROAD = 3
    TIMEOUT = 4


#: Event behaviours (``on_goal`` / ``on_collision`` / ``on_offroad``).
EVENT_RULES: dict[str, int] = {"remove": 0, "stop": 1, "ignore": 2}
DYNAMICS_MODELS: dict[str, int] = {"jerk": 0, "classic": 1}
CONTROLLER_NAMES: dict[str, Controller] = {c.name.lower(): c for c in Controller if c != Controller.NONE}

# ----------------------------------------------------------------------------- action sets
#: Jerk model (BehaviorBench / PufferDrive "jerk"): index = long_idx * 3 + lat_idx.
JERK_LONG = np.array([-15.0, -4.0, 0.0, 4.0], np.float32)  # m/s^3
JERK_LAT = np.array([-4.0, 0.0, 4.0], np.float32)          # m/s^3
#: Classic bicycle (GPUDrive / PufferDrive): index = accel_idx * 13 + steer_idx.
CLASSIC_ACCEL = np.array([-4.0, -2.667, -1.333, 0.0, 1.333, 2.667, 4.0], np.float32)  # m/s^2
#: PufferDrive's steering table, rounded to three decimals (not exactly linspace(-1, 1, 13)).
CLASSIC_STEER = np.array([-1.0, -0.833, -0.667, -0.5, -0.333, -0.167, 0.0,
                          0.167, 0.333, 0.5, 0.667, 0.833, 1.0], np.float32)               # rad


# ----------------------------------------------------------------------------- goal criterion
@dataclasses.dataclass(frozen=True)
class GoalCriterion:
    """A fixed goal test: reached when |pos - goal| < ``radius`` and |speed| <= ``speed``."""

    name: str
    radius: float  # m
    speed: float   # m/s


#: BehaviorBench's evaluation goal test (DESIGN.md, "Evaluation goal criterion"): radius 2 m
#: and goal speed 100 m/s, i.e. no effective speed limit. Every deployment condition is tested
#: with it, so sweeping the condition changes the driving style and never the task.
EVAL_GOAL = GoalCriterion("evaluation", radius=2.0, speed=100.0)
#: Goal tests by name (``SimConfig.goal_criterion``): "condition" (None here) tests each agent
#: with the goal_radius / goal_speed of its own reward condition (self-play training, where
#: every agent keeps the task fields drawn from p_train); "evaluation" is :data:`EVAL_GOAL`.
GOAL_CRITERIA: dict[str, GoalCriterion | None] = {"condition": None, "evaluation": EVAL_GOAL}


def num_actions(dynamics: str) -> int:
    """Size of the discrete action set of a dynamics model (12 jerk, 91 classic)."""
    if dynamics == "jerk":
        return JERK_LONG.size * JERK_LAT.size
    if dynamics == "classic":
        return CLASSIC_ACCEL.size * CLASSIC_STEER.size
    raise ValueError(f"dynamics: unknown model {dynamics!r}; accepted: {sorted(DYNAMICS_MODELS)}")


def known_fields(cls: type, values: Mapping[str, Any], name: str) -> dict[str, Any]:
    """``values`` as a dict after checking every key is a field of the dataclass ``cls``.

    The check behind the ``from_dict`` of the settings dataclasses (``SimConfig`` keeps its
    own, which also takes None or a ``SimConfig``): a key that is not a field raises ``ValueError`` naming the config (``name``), the unknown keys and the
    accepted ones, before anything is built.
    """
    if not isinstance(values, Mapping):
        raise ValueError(f"{name}: expected a mapping, got {type(values).__name__}")
    accepted = sorted(f.name for f in dataclasses.fields(cls))
    unknown = sorted(set(values) - set(accepted))
    if unknown:
        raise ValueError(f"{name}: unknown keys {unknown}; accepted: {accepted}")
    return dict(values)


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Simulator settings (frozen). Units: metres, seconds, radians unless stated.

    Attributes:
        dynamics: "jerk" (12 actions, default) or "classic" (91 actions, PufferDrive's bicycle).
        dt: decision period, s.
        episode_steps: decisions per episode; agents still running then time out.
        num_partners: K, partners in the observation.
        num_road: M, road segments in the observation.
        partner_radius: observation range for partners, m (also their position scale).
        road_radius: observation range for road segments, m (also their position scale).
        on_goal, on_collision, on_offroad: "remove" (agent leaves the world: not observed,
            not collidable), "stop" (agent ends its episode and stays as a static obstacle;
            its controller becomes STATIC) or "ignore" (recorded only; it drives on).
            Removal applies to POLICY and IDM agents; REPLAY and STATIC agents are scenery
            (their events are recorded, they are never removed by them).
        box_scale: scale of every box's length and width for collision and off-road
            geometry (1.0 = logged size; PufferDrive's tests use 0.7). Observations and
            rendering keep the logged size. The classic step's yaw rate divides by
            ``box_scale`` x the logged length (PufferDrive shrinks the agents it controls to
            0.7 at load and its bicycle divides by that length), so ``box_scale=0.7`` with
            ``dynamics="classic"`` reproduces PufferDrive's trajectories on WOMD; the jerk
            model's wheelbase stays 0.6 x the logged length.
        default_controller: controller of controllable agents at reset ("policy").
        other_controller: controller of the other agents at reset ("replay").
        grid_cell: side of the per-scenario uniform grid cells, m.
        lane_radius: lane queries look for the nearest lane centreline within this, m.
        align_deg: aligned when the heading error to the lane is below this, degrees.
        lane_width: nominal lane width, m (two-lane test).
        collide_types: whether pedestrians and cyclists collide (vehicles always do).
        observe_all: compute observations for every alive agent. By default (False) only
            alive POLICY agents and task agents (controllable at reset: vehicles valid at t0
            with a goal >= 2 m away, whatever their controller) are observed; scenery
            (parked cars, pedestrians, agents without a task) observes zeros, which saves
            most of the observation cost on WOMD scenes.
        goal_criterion: the goal test (:data:`GOAL_CRITERIA`): "condition" (default: each
            agent's own goal_radius / goal_speed condition fields, as in training) or
            "evaluation" (:data:`EVAL_GOAL`, 2 m and 100 m/s for every agent, whatever its
            condition; the evaluator, ``selfplay_outcomes`` and a Drive env with a fixed
            deployment condition use it).
        road_simplify_tol: road polylines are simplified to this chord tolerance, m.
        road_max_segment: ... and to segments no longer than this, m.
        idm_v0, idm_accel, idm_brake, idm_headway, idm_min_gap, idm_lookahead: IDM parameters
            (desired speed m/s, max accel m/s^2, comfortable braking m/s^2, time headway s,
            jam gap m, leader search distance along the path m). Defaults are BehaviorBench's
            (v0 15, a 1.0, b 3.0, T 1.5, s0 1). ``idm_v0 = 0`` uses each agent's largest
            logged speed instead; agents whose log moves less than 1 m stay put either way.
    """

    dynamics: str = "jerk"
    dt: float = 0.1
    episode_steps: int = 91
    num_partners: int = 16
    num_road: int = 64
    partner_radius: float = 50.0
    road_radius: float = 50.0
    on_goal: str = "remove"
    on_collision: str = "remove"
    on_offroad: str = "remove"
    box_scale: float = 1.0
    default_controller: str = "policy"
    other_controller: str = "replay"
    grid_cell: float = 5.0
    lane_radius: float = 4.0
    align_deg: float = 15.0
    lane_width: float = 3.7
    collide_types: bool = True
    observe_all: bool = False
    goal_criterion: str = "condition"
    road_simplify_tol: float = 0.05
    road_max_segment: float = 10.0
    idm_v0: float = 15.0
    idm_accel: float = 1.0
    idm_brake: float = 3.0
    idm_headway: float = 1.5
    idm_min_gap: float = 1.0
    idm_lookahead: float = 40.0

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "SimConfig":
        """Build from a mapping; unknown keys raise ``ValueError`` listing the valid ones."""
        if d is None:
            return cls()
        if isinstance(d, SimConfig):
            return d
        if not isinstance(d, Mapping):
            raise ValueError(f"config: expected a mapping, got {type(d).__name__}")
        valid = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(d) - set(valid))
        if unknown:
            raise ValueError(f"config: unknown key(s) {unknown}; valid keys: {valid}")
        return cls(**dict(d))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def replace(self, **changes: Any) -> "SimConfig":
        """A copy with some fields changed (validated like the constructor)."""
        return SimConfig.from_dict({**self.to_dict(), **changes})

    def __post_init__(self) -> None:
        def bad(field: str, why: str) -> ValueError:
            return ValueError(f"SimConfig.{field}: {why} (got {getattr(self, field)!r})")

        if self.dynamics not in DYNAMICS_MODELS:
            raise bad("dynamics", f"must be one of {sorted(DYNAMICS_MODELS)}")
        for name in ("on_goal", "on_collision", "on_offroad"):
            if getattr(self, name) not in EVENT_RULES:
                raise bad(name, f"must be one of {sorted(EVENT_RULES)}")
        for name in ("default_controller", "other_controller"):
            if getattr(self, name) not in CONTROLLER_NAMES:
                raise bad(name, f"must be one of {sorted(CONTROLLER_NAMES)}")
        for name in ("episode_steps", "num_partners", "num_road"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise bad(name, "must be an integer")
        if not 1 <= self.episode_steps <= 91:
            # logs hold 91 states; replayed agents hold their last logged state past step 90
            raise bad("episode_steps", "must be in [1, 91]")
        if self.num_partners < 0 or self.num_partners > 1024:
            raise bad("num_partners", "must be in [0, 1024]")
        if self.num_road < 0 or self.num_road > 4096:
            raise bad("num_road", "must be in [0, 4096]")
        positive = ("dt", "partner_radius", "road_radius", "box_scale", "grid_cell", "lane_radius",
                    "align_deg", "lane_width", "road_max_segment", "idm_accel",
                    "idm_brake", "idm_headway", "idm_lookahead")
        for name in positive:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) \
                    or not np.isfinite(v) or v <= 0:
                raise bad(name, "must be a finite number > 0")
        for name in ("road_simplify_tol", "idm_min_gap", "idm_v0"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) \
                    or not np.isfinite(v) or v < 0:
                raise bad(name, "must be a finite number >= 0")
        if self.box_scale > 2.0:
            raise bad("box_scale", "must be in (0, 2]")
        if self.align_deg >= 180.0:
            raise bad("align_deg", "must be below 180")
        if self.goal_criterion not in GOAL_CRITERIA:
            raise bad("goal_criterion", f"must be one of {sorted(GOAL_CRITERIA)}")
        for name in ("collide_types", "observe_all"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise bad(name, "must be a bool")

    # ------------------------------------------------------------------ derived
    @property
    def num_actions(self) -> int:
        return num_actions(self.dynamics)


__all__ = [
    "SimConfig", "Controller", "Outcome", "EVENT_RULES", "DYNAMICS_MODELS", "CONTROLLER_NAMES",
    "JERK_LONG", "JERK_LAT", "CLASSIC_ACCEL", "CLASSIC_STEER", "num_actions",
    "GoalCriterion", "EVAL_GOAL", "GOAL_CRITERIA",
]
