"""Mutable simulator state and control, as Warp structs of (W, ...) device arrays.

Everything a future step reads lives in :class:`State` (so a snapshot of a world is a
copy of its rows of every field). Outputs that are pure functions of the state (the
observation) live apart and are recomputed after a restore. Per-step scratch, written and
read within one step and rewritten by every step before anyone reads it, lives in
:class:`StepScratch` (one per Simulator, next to its State): snapshots, restores and
``state_dict`` leave it out. Units: m, s, rad, m/s, m/s^2.

Shapes: W worlds, A agent slots, NC = 10 condition fields, NT reward terms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from cpsim.conditions import NUM_CONDITION_FIELDS

#: Reward terms, in the order of the last axis of ``reward_raw`` / ``reward_w``.
REWARD_TERMS: tuple[str, ...] = (
    "goal", "collision", "offroad", "comfort", "lane_align", "vel_align", "lane_center",
    "reverse", "velocity", "time",
)
NUM_REWARD_TERMS = len(REWARD_TERMS)
#: Positions kept per agent for the at-fault lane-divider rule (its last 4 positions).
POS_HISTORY = 4

#: Metric accumulators exposed as ``Simulator.metrics`` (each (W, A)).
METRIC_FIELDS: tuple[str, ...] = (
    "steps_alive", "comfort_violations", "aligned_steps", "lateral_offset_sum",
    "first_collision_step", "collision_partner", "first_offroad_step", "goal_step", "at_fault",
)


@wp.struct
class State:
    """Per-world and per-agent state. All arrays have the world as leading axis."""

    # per world (W,)
    scenario: wp.array(dtype=wp.int32)          # pool index of the world's scenario
    step_count: wp.array(dtype=wp.int32)        # decisions taken since reset
    world_done: wp.array(dtype=wp.bool)         # step_count == episode_steps or no POLICY agent alive
    # per agent (W, A)
    agent_index: wp.array2d(dtype=wp.int32)     # scenario agent index (-1 empty slot)
    agent_row: wp.array2d(dtype=wp.int32)       # row in the model's log arrays (-1 empty)
    controller: wp.array2d(dtype=wp.int32)      # Controller
    task_agent: wp.array2d(dtype=wp.bool)       # controllable at reset (vehicle with a task)
    alive: wp.array2d(dtype=wp.bool)            # occupied slot, agent not removed
    finished: wp.array2d(dtype=wp.bool)         # the agent's episode ended (done was emitted)
    pos: wp.array2d(dtype=wp.vec2f)             # box centre, m
    heading: wp.array2d(dtype=wp.float32)       # rad
    vel: wp.array2d(dtype=wp.vec2f)             # world-frame velocity, m/s
    speed: wp.array2d(dtype=wp.float32)         # signed speed along the heading, m/s
    accel: wp.array2d(dtype=wp.float32)         # longitudinal acceleration, m/s^2
    lat_accel: wp.array2d(dtype=wp.float32)     # lateral acceleration, m/s^2
    jerk: wp.array2d(dtype=wp.float32)          # longitudinal jerk of the last step, m/s^3
    lat_jerk: wp.array2d(dtype=wp.float32)      # lateral jerk of the last step, m/s^3
    steer: wp.array2d(dtype=wp.float32)         # steering angle, rad
    prev_pos: wp.array2d(dtype=wp.vec2f)        # pose before the last step (swept off-road test)
    prev_heading: wp.array2d(dtype=wp.float32)
    prev_vel: wp.array2d(dtype=wp.vec2f)        # velocity before the last step (at-fault rules)
    pos_hist: wp.array3d(dtype=wp.vec2f)        # (W, A, POS_HISTORY) ring of pre-step positions:
                                                # slot step_count % POS_HISTORY = the last one
    size: wp.array2d(dtype=wp.vec2f)            # logged (length, width), m
    agent_type: wp.array2d(dtype=wp.int32)      # AgentType
    goal: wp.array2d(dtype=wp.vec2f)            # m
    conditions: wp.array3d(dtype=wp.float32)    # (W, A, 10) raw reward conditions
    outcome: wp.array2d(dtype=wp.int32)         # Outcome (sticky)
    done: wp.array2d(dtype=wp.bool)             # the agent's episode ended on the last step
    terminated: wp.array2d(dtype=wp.bool)
    truncated: wp.array2d(dtype=wp.bool)
    reward: wp.array2d(dtype=wp.float32)
    reward_raw: wp.array3d(dtype=wp.float32)    # (W, A, NT)
    reward_w: wp.array3d(dtype=wp.float32)      # (W, A, NT)
    idm_s: wp.array2d(dtype=wp.float32)         # arc position along the logged path, m
    idm_k: wp.array2d(dtype=wp.int32)           # path segment cursor
    lane_err: wp.array2d(dtype=wp.float32)      # signed heading error to the nearest lane, rad
    lane_offset: wp.array2d(dtype=wp.float32)   # signed lateral offset (left +), m
    has_lane: wp.array2d(dtype=wp.bool)         # a lane centreline lies within lane_radius
    # metrics accumulators (W, A)
    steps_alive: wp.array2d(dtype=wp.int32)
    comfort_violations: wp.array2d(dtype=wp.int32)
    aligned_steps: wp.array2d(dtype=wp.int32)
    lateral_offset_sum: wp.array2d(dtype=wp.float32)
    first_collision_step: wp.array2d(dtype=wp.int32)
    collision_partner: wp.array2d(dtype=wp.int32)
    first_offroad_step: wp.array2d(dtype=wp.int32)
    goal_step: wp.array2d(dtype=wp.int32)
    at_fault: wp.array2d(dtype=wp.bool)


@wp.struct
class StepScratch:
    """Per-step scratch (W, A) of a Simulator: written by one kernel of a step and read by a
    later kernel of the same step, never carried from one step to the next (so never part of
    a snapshot). Kernels take it as the parameter ``scratch`` (their ``Reads:`` / ``Writes:``
    lines name its fields ``scratch.<field>``)."""

    # present: the agent takes part in this step's events (alive when the step began and
    # still in the world after the motion). Written for every slot by the motion kernel,
    # read by the prepare and events kernels of the same step.
    # Why not ``alive``: the events kernel clears ``alive`` of an agent it removes (goal,
    # collision, off-road) in that agent's own thread while the other threads of the world
    # test their agents against everyone. Reading the others' ``alive`` there would make
    # whether an agent removed this step is still a collision partner depend on thread
    # (or, on CPU, slot) order: one side of a collision could miss it. ``present`` does not
    # change during the events, so every agent sees the same set and both sides record a
    # collision.
    present: wp.array2d(dtype=wp.bool)
    # idm_accel: IDM command of this step, written by the IDM kernel for every live IDM agent
    # of a running world and read by the motion kernel for exactly those agents (the IDM
    # kernel runs in every step where some agent is on IDM).
    idm_accel: wp.array2d(dtype=wp.float32)


#: Fields with one entry per world (the others are per agent slot).
_PER_WORLD = {"scenario": wp.int32, "step_count": wp.int32, "world_done": wp.bool}


def state_field_names() -> tuple[str, ...]:
    """Every field of :class:`State`, in declaration order."""
    return tuple(State.vars.keys())


def allocate_state(num_worlds: int, max_agents: int, device: str) -> State:
    """Zero-initialised state for W worlds x A slots (empty slots: index -1, controller NONE)."""
    s = State()
    W, A = num_worlds, max_agents
    for name in state_field_names():
        var = State.vars[name]
        dtype = var.type.dtype
        if name in _PER_WORLD:
            shape: tuple[int, ...] = (W,)
        elif name == "conditions":
            shape = (W, A, NUM_CONDITION_FIELDS)
        elif name in ("reward_raw", "reward_w"):
            shape = (W, A, NUM_REWARD_TERMS)
        elif name == "pos_hist":
            shape = (W, A, POS_HISTORY)
        else:
            shape = (W, A)
        setattr(s, name, wp.zeros(shape, dtype=dtype, device=device))
    s.agent_index.fill_(-1)
    s.agent_row.fill_(-1)
    s.controller.fill_(4)  # Controller.NONE
    for name in ("first_collision_step", "collision_partner", "first_offroad_step", "goal_step"):
        getattr(s, name).fill_(-1)
    return s


def scratch_field_names() -> tuple[str, ...]:
    """Every field of :class:`StepScratch`, in declaration order."""
    return tuple(StepScratch.vars.keys())


def allocate_scratch(num_worlds: int, max_agents: int, device: str) -> StepScratch:
    """Zero-initialised per-step scratch for W worlds x A slots (every field (W, A))."""
    s = StepScratch()
    for name in scratch_field_names():
        setattr(s, name, wp.zeros((num_worlds, max_agents), dtype=StepScratch.vars[name].type.dtype,
                                  device=device))
    return s


def state_to_numpy(state: State) -> dict[str, np.ndarray]:
    """Copies of every field as NumPy arrays (vec2 fields get a trailing axis of 2)."""
    return {name: getattr(state, name).numpy().copy() for name in state_field_names()}


@dataclass
class Control:
    """Inputs of one step: ``actions`` (W, A) int32 action indices (POLICY agents read them)."""

    actions: wp.array

    @classmethod
    def allocate(cls, num_worlds: int, max_agents: int, device: str) -> "Control":
        return cls(actions=wp.zeros((num_worlds, max_agents), dtype=wp.int32, device=device))


__all__ = ["State", "StepScratch", "Control", "REWARD_TERMS", "NUM_REWARD_TERMS", "METRIC_FIELDS", "POS_HISTORY",
           "allocate_state", "allocate_scratch", "state_to_numpy", "state_field_names",
           "scratch_field_names"]
