"""Run-time parameters passed to every kernel, and the name of the shared Warp module.

All kernels of ``cpsim.kernels`` are registered in one Warp module (:data:`KERNEL_MODULE`)
so the whole simulator compiles once (a few seconds, then milliseconds from the kernel
cache). Configuration values travel in :class:`Params` at run time: changing the config
never recompiles.

Every kernel has a *launcher* beside it in its module (a ``launch_*`` function marked with
:func:`launcher`): the one place that knows the kernel's parameter order. A launcher takes the
kernel's arguments by name plus ``dim``, ``device`` and ``record``, passes the arrays the
kernel writes as ``outputs=`` of ``wp.launch`` (its other arguments as ``inputs=``), names
the State / StepScratch fields it writes in its docstring's ``Writes:`` line, and returns
``wp.launch``'s result: the recorded command when ``record`` (``record_cmd=True``: the
Simulator records the launches of a step and of a reset once and replays them), else None.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import warp as wp

from cpsim.config import DYNAMICS_MODELS, EVENT_RULES, GOAL_CRITERIA, Controller, Outcome, SimConfig
from cpsim.scenario.datatypes import AgentType

#: The single Warp module every simulator kernel belongs to.
KERNEL_MODULE = "cpsim.kernels"
#: Options of that module: no adjoints (nothing differentiates through the simulator).
KERNEL_OPTIONS = {"enable_backward": False}
wp.set_module_options(KERNEL_OPTIONS, module=KERNEL_MODULE)

# Controller / outcome / type / event-rule codes as Warp constants, generated from the
# Python enums so the two can never disagree (one source: cpsim.config / datatypes).
POLICY = wp.constant(int(Controller.POLICY))
REPLAY = wp.constant(int(Controller.REPLAY))
IDM = wp.constant(int(Controller.IDM))
STATIC = wp.constant(int(Controller.STATIC))
NO_CONTROLLER = wp.constant(int(Controller.NONE))
RUNNING = wp.constant(int(Outcome.RUNNING))
GOAL = wp.constant(int(Outcome.GOAL))
COLLISION = wp.constant(int(Outcome.COLLISION))
OFFROAD = wp.constant(int(Outcome.OFFROAD))
TIMEOUT = wp.constant(int(Outcome.TIMEOUT))
VEHICLE = wp.constant(int(AgentType.VEHICLE))
#: logs hold 91 states (WOMD): replayed agents keep their last logged state past it
LAST_LOG_STEP = wp.constant(90)
RULE_REMOVE = wp.constant(EVENT_RULES["remove"])
RULE_STOP = wp.constant(EVENT_RULES["stop"])
RULE_IGNORE = wp.constant(EVENT_RULES["ignore"])


@wp.struct
class Params:
    """Scalar settings of a run (see :class:`cpsim.SimConfig` for meanings and units)."""

    dt: float
    episode_steps: int
    dynamics: int           # 0 jerk, 1 classic
    num_partners: int       # K
    num_road: int           # M
    partner_radius: float
    road_radius: float
    on_goal: int            # 0 remove, 1 stop, 2 ignore
    on_collision: int
    on_offroad: int
    box_scale: float
    lane_radius: float
    align_rad: float
    lane_width: float
    collide_types: int
    road_max_segment: float
    idm_v0: float
    idm_accel: float
    idm_brake: float
    idm_headway: float
    idm_min_gap: float
    idm_lookahead: float
    obs_dim: int            # D
    obs_condition: int      # first index of the condition slice
    obs_partners: int       # first index of the partner block
    obs_road: int           # first index of the road block
    partner_features: int
    road_features: int
    observe_all: int        # 1: every alive agent is observed; 0: POLICY and task agents only
    goal_fixed: int         # 1: every agent's goal test uses goal_radius / goal_speed below;
    goal_radius: float      #    0: each agent's own condition fields (SimConfig.goal_criterion)
    goal_speed: float


def make_params(config: SimConfig, layout) -> Params:
    """Fill :class:`Params` from a config and an :class:`cpsim.observation.ObsLayout`."""
    p = Params()
    p.dt = float(config.dt)
    p.episode_steps = int(config.episode_steps)
    p.dynamics = DYNAMICS_MODELS[config.dynamics]
    p.num_partners = int(config.num_partners)
    p.num_road = int(config.num_road)
    p.partner_radius = float(config.partner_radius)
    p.road_radius = float(config.road_radius)
    p.on_goal = EVENT_RULES[config.on_goal]
    p.on_collision = EVENT_RULES[config.on_collision]
    p.on_offroad = EVENT_RULES[config.on_offroad]
    p.box_scale = float(config.box_scale)
    p.lane_radius = float(config.lane_radius)
    p.align_rad = math.radians(config.align_deg)
    p.lane_width = float(config.lane_width)
    p.collide_types = int(bool(config.collide_types))
    p.road_max_segment = float(config.road_max_segment)
    p.idm_v0 = float(config.idm_v0)
    p.idm_accel = float(config.idm_accel)
    p.idm_brake = float(config.idm_brake)
    p.idm_headway = float(config.idm_headway)
    p.idm_min_gap = float(config.idm_min_gap)
    p.idm_lookahead = float(config.idm_lookahead)
    p.obs_dim = int(layout.size)
    p.obs_condition = int(layout.condition.start)
    p.obs_partners = int(layout.partners.start)
    p.obs_road = int(layout.road.start)
    p.partner_features = int(layout.partner_features)
    p.road_features = int(layout.road_features)
    p.observe_all = int(bool(config.observe_all))
    criterion = GOAL_CRITERIA[config.goal_criterion]
    p.goal_fixed = int(criterion is not None)
    p.goal_radius = float(criterion.radius) if criterion is not None else 0.0
    p.goal_speed = float(criterion.speed) if criterion is not None else 0.0
    return p


def launcher(*kernels: wp.Kernel) -> Callable:
    """Mark a function as the launcher of ``kernels`` (a kernel and its variants with the same
    parameters, e.g. a per-world one): ``fn.kernels`` lists them, and
    ``tests/cpsim/test_kernel_contracts.py`` checks every kernel has exactly one launcher whose
    ``Writes:`` line matches the kernel's."""

    def mark(fn: Callable) -> Callable:
        fn.kernels = kernels
        return fn

    return mark


def launch(kernel: wp.Kernel, kernels: Sequence[wp.Kernel], dim: Any, inputs: list, outputs: list | None = None,
           device: Any = None, record: bool = False) -> Any:
    """``wp.launch`` for a launcher: ``kernel`` must be one of its ``kernels``; returns the
    recorded command when ``record``, else None."""
    if kernel not in kernels:
        raise ValueError(f"{kernel.key}: not launched by this launcher (expects one of "
                         f"{[k.key for k in kernels]})")
    return wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs or [], device=device, record_cmd=record)


__all__ = ["KERNEL_MODULE", "KERNEL_OPTIONS", "Params", "make_params", "launcher", "launch"]
