"""State initialisation (reset) and world-to-world state copies (snapshot / restore).

``copy_worlds_kernel`` copies every field of :class:`cpsim.state.State` from world
``src_idx[i]`` of one state to world ``dst_idx[i]`` of another (or the same) state, in one
launch over (n, A): a snapshot gathers worlds into a compact snapshot state, a restore
scatters them back (one-to-many by repeating a source index). Cost scales with the worlds
touched. ``tests/cpsim/test_sim_snapshot.py`` checks that every State field is copied. The
per-step :class:`cpsim.state.StepScratch` is neither copied nor reset: every step rewrites it
before reading it.

``reset_kernel`` initialises the listed worlds from their scenario's log at t0. It reads the
slot, controller and task tables of the scenario (uploaded once per Simulator) and the
staged world / scenario / condition buffers, so a reset is one recorded launch with no
per-reset allocation (plus the observation of the reset worlds).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from cpsim.kernels.common import KERNEL_MODULE, NO_CONTROLLER, POLICY, RUNNING, STATIC, Params, launch, launcher
from cpsim.kernels.dynamics import signed_speed
from cpsim.kernels.geometry import lane_query
from cpsim.kernels.observation import tracked_role
from cpsim.model_arrays import ModelArrays
from cpsim.state import State


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def copy_worlds_kernel(src: State, dst: State, src_idx: wp.array(dtype=wp.int32),
                       dst_idx: wp.array(dtype=wp.int32)):
    """dst world dst_idx[i] <- src world src_idx[i], every field (over (n, A)).

    Reads: src.*
    Writes: dst.*
    """
    i, a = wp.tid()
    s = src_idx[i]
    d = dst_idx[i]
    if a == 0:
        dst.scenario[d] = src.scenario[s]
        dst.step_count[d] = src.step_count[s]
        dst.world_done[d] = src.world_done[s]
    dst.agent_index[d, a] = src.agent_index[s, a]
    dst.agent_row[d, a] = src.agent_row[s, a]
    dst.controller[d, a] = src.controller[s, a]
    dst.task_agent[d, a] = src.task_agent[s, a]
    dst.alive[d, a] = src.alive[s, a]
    dst.finished[d, a] = src.finished[s, a]
    dst.pos[d, a] = src.pos[s, a]
    dst.heading[d, a] = src.heading[s, a]
    dst.vel[d, a] = src.vel[s, a]
    dst.speed[d, a] = src.speed[s, a]
    dst.accel[d, a] = src.accel[s, a]
    dst.lat_accel[d, a] = src.lat_accel[s, a]
    dst.jerk[d, a] = src.jerk[s, a]
    dst.lat_jerk[d, a] = src.lat_jerk[s, a]
    dst.steer[d, a] = src.steer[s, a]
    dst.prev_pos[d, a] = src.prev_pos[s, a]
    dst.prev_heading[d, a] = src.prev_heading[s, a]
    dst.prev_vel[d, a] = src.prev_vel[s, a]
    for f in range(src.pos_hist.shape[2]):
        dst.pos_hist[d, a, f] = src.pos_hist[s, a, f]
    dst.size[d, a] = src.size[s, a]
    dst.agent_type[d, a] = src.agent_type[s, a]
    dst.goal[d, a] = src.goal[s, a]
    for f in range(src.conditions.shape[2]):
        dst.conditions[d, a, f] = src.conditions[s, a, f]
    dst.outcome[d, a] = src.outcome[s, a]
    dst.done[d, a] = src.done[s, a]
    dst.terminated[d, a] = src.terminated[s, a]
    dst.truncated[d, a] = src.truncated[s, a]
    dst.reward[d, a] = src.reward[s, a]
    for f in range(src.reward_raw.shape[2]):
        dst.reward_raw[d, a, f] = src.reward_raw[s, a, f]
    for f in range(src.reward_w.shape[2]):
        dst.reward_w[d, a, f] = src.reward_w[s, a, f]
    dst.idm_s[d, a] = src.idm_s[s, a]
    dst.idm_k[d, a] = src.idm_k[s, a]
    dst.lane_err[d, a] = src.lane_err[s, a]
    dst.lane_offset[d, a] = src.lane_offset[s, a]
    dst.has_lane[d, a] = src.has_lane[s, a]
    dst.steps_alive[d, a] = src.steps_alive[s, a]
    dst.comfort_violations[d, a] = src.comfort_violations[s, a]
    dst.aligned_steps[d, a] = src.aligned_steps[s, a]
    dst.lateral_offset_sum[d, a] = src.lateral_offset_sum[s, a]
    dst.first_collision_step[d, a] = src.first_collision_step[s, a]
    dst.collision_partner[d, a] = src.collision_partner[s, a]
    dst.first_offroad_step[d, a] = src.first_offroad_step[s, a]
    dst.goal_step[d, a] = src.goal_step[s, a]
    dst.at_fault[d, a] = src.at_fault[s, a]


@launcher(copy_worlds_kernel)
def launch_copy_worlds(src: State, dst: State, src_idx: wp.array, dst_idx: wp.array, *, dim: Any,
                       device: Any = None, record: bool = False) -> Any:
    """Launch :func:`copy_worlds_kernel` over ``dim`` = (n, A): ``dst`` world ``dst_idx[i]`` <-
    ``src`` world ``src_idx[i]``; ``src``, ``src_idx`` and ``dst_idx`` are read only.

    Writes: dst.*
    """
    return launch(copy_worlds_kernel, launch_copy_worlds.kernels, dim, [src, dst, src_idx, dst_idx],
                  device=device, record=record)


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def reset_kernel(state: State, model: ModelArrays, params: Params, worlds: wp.array(dtype=wp.int32),
                 scenario: wp.array(dtype=wp.int32), slot_table: wp.array2d(dtype=wp.int32),
                 ctrl_table: wp.array2d(dtype=wp.int32), task_table: wp.array2d(dtype=wp.bool),
                 conditions: wp.array3d(dtype=wp.float32), track_all: int, trig: wp.array2d(dtype=wp.vec2f)):
    """Initialise world worlds[i] with pool scenario g = scenario[i]; slot a holds scenario
    agent slot_table[g, a] (-1 empty) driven by ctrl_table[g, a]; task_table[g, a] marks the
    controllable agents; conditions[i, a] are its raw conditions; trig[w, a] gets the (cos, sin)
    of the heading (over (n, A)). The lane fields are computed for tracked agents only.

    Reads: -
    Writes: *
    """
    i, a = wp.tid()
    w = worlds[i]
    g = scenario[i]
    num = slot_table.shape[1]
    if a == 0:
        state.scenario[w] = g
        state.step_count[w] = 0
        any_policy = bool(False)
        for b in range(num):
            if slot_table[g, b] >= 0 and ctrl_table[g, b] == POLICY:
                any_policy = bool(True)
        state.world_done[w] = not any_policy
    local = slot_table[g, a]
    row = int(-1)
    ctrl = NO_CONTROLLER
    if local >= 0:
        row = model.agent_first[g] + local
        ctrl = ctrl_table[g, a]
    task = task_table[g, a] and local >= 0
    state.agent_index[w, a] = local
    state.agent_row[w, a] = row
    state.controller[w, a] = ctrl
    state.task_agent[w, a] = task
    for f in range(conditions.shape[2]):
        state.conditions[w, a, f] = conditions[i, a, f]
    occupied = row >= 0
    state.alive[w, a] = occupied
    state.finished[w, a] = False
    pos = wp.vec2f(0.0, 0.0)
    heading = float(0.0)
    vel = wp.vec2f(0.0, 0.0)
    size = wp.vec2f(0.0, 0.0)
    goal = wp.vec2f(0.0, 0.0)
    atype = int(0)
    if occupied:
        pos = model.log_xy[row, 0]
        heading = model.log_heading[row, 0]
        vel = model.log_vel[row, 0]
        size = model.size[row]
        goal = model.goal[row]
        atype = model.agent_type[row]
        if ctrl == STATIC:
            vel = wp.vec2f(0.0, 0.0)
    state.pos[w, a] = pos
    state.heading[w, a] = heading
    trig[w, a] = wp.vec2f(wp.cos(heading), wp.sin(heading))
    state.vel[w, a] = vel
    state.speed[w, a] = signed_speed(vel, heading)
    state.accel[w, a] = 0.0
    state.lat_accel[w, a] = 0.0
    state.jerk[w, a] = 0.0
    state.lat_jerk[w, a] = 0.0
    state.steer[w, a] = 0.0
    state.prev_pos[w, a] = pos
    state.prev_heading[w, a] = heading
    state.prev_vel[w, a] = vel
    for f in range(state.pos_hist.shape[2]):
        state.pos_hist[w, a, f] = pos
    state.size[w, a] = size
    state.agent_type[w, a] = atype
    state.goal[w, a] = goal
    state.outcome[w, a] = RUNNING
    state.done[w, a] = False
    state.terminated[w, a] = False
    state.truncated[w, a] = False
    state.reward[w, a] = 0.0
    for k in range(state.reward_raw.shape[2]):
        state.reward_raw[w, a, k] = 0.0
        state.reward_w[w, a, k] = 0.0
    state.idm_s[w, a] = 0.0
    state.idm_k[w, a] = 0
    has_lane = bool(False)
    err = float(0.0)
    offset = float(0.0)
    if occupied and tracked_role(ctrl, task, False, a, params.observe_all, track_all):
        sid, ld, off, e = lane_query(model, g, pos, heading, params.lane_radius)
        if sid >= 0:
            has_lane = bool(True)
            err = e
            offset = off
    state.has_lane[w, a] = has_lane
    state.lane_err[w, a] = err
    state.lane_offset[w, a] = offset
    state.steps_alive[w, a] = 0
    state.comfort_violations[w, a] = 0
    state.aligned_steps[w, a] = 0
    state.lateral_offset_sum[w, a] = 0.0
    state.first_collision_step[w, a] = -1
    state.collision_partner[w, a] = -1
    state.first_offroad_step[w, a] = -1
    state.goal_step[w, a] = -1
    state.at_fault[w, a] = False


@launcher(reset_kernel)
def launch_reset(state: State, model: ModelArrays, params: Params, worlds: wp.array, scenario: wp.array,
                 slot_table: wp.array, ctrl_table: wp.array, task_table: wp.array, conditions: wp.array,
                 track_all: int, trig: wp.array, *, dim: Any, device: Any = None, record: bool = False) -> Any:
    """Launch :func:`reset_kernel` over ``dim`` = (len(worlds), A); the staged worlds, scenarios
    and conditions and the slot / controller / task tables are read only. Output: ``trig``.

    Writes: *
    """
    return launch(reset_kernel, launch_reset.kernels, dim,
                  [state, model, params, worlds, scenario, slot_table, ctrl_table, task_table, conditions,
                   int(track_all)], [trig], device=device, record=record)


__all__ = ["copy_worlds_kernel", "reset_kernel", "launch_copy_worlds", "launch_reset"]
