"""Events, outcomes, removal, reward and metrics of a step; per-world bookkeeping.

``events_kernel`` (over (W, A), CUDA) and ``events_world_kernel`` (over W, looping over the
slots, CPU) run :func:`agent_events` after the motion and ``prepare_kernel``. For each
*tracked* agent present in the step (POLICY, IDM, task agents, slot 0; see
:func:`cpsim.kernels.observation.tracked_role`) it tests, against the poses after the motion
(*scenery*, the other REPLAY / STATIC agents, gets collisions with tracked agents, off-road,
and timeout only (no task, so no goal); ``Simulator(track_all=True)`` tracks everyone):

* collision with any other present collidable agent (SAT, distance pre-filter; scaled boxes),
  the partner being the nearest colliding one, and its collision case / fault (BehaviorBench's
  rules on the pre-contact state, ``cpsim.kernels.geometry``);
* off-road (vehicles only): a road-edge segment of the cell's candidate list hits the box at
  its current pose or crosses a corner path from the previous pose;
* goal (task agents only; an agent without a task, e.g. a parked car driven by a traffic
  regime, never arrives): |pos - goal| < goal_radius and |speed| <= goal_speed (the agent's
  condition, or the fixed criterion of ``SimConfig.goal_criterion`` for every agent);
* the nearest lane (heading error, lateral offset) for metrics, reward and observation.

Then: outcome (sticky; collision > off-road > goal within one step), metrics accumulators,
reward terms, removal (POLICY and IDM agents only, per ``on_*`` rule; the strongest of
remove > stop > ignore among the step's events: remove clears ``alive``, stop switches the
controller to STATIC so the agent holds its position from the next step on; both end the
agent's episode: done and terminated), and timeout (step == episode_steps: every agent
still alive whose episode has not ended gets done and truncated, outcome TIMEOUT if still
RUNNING). Each thread writes only its own agent, so the kernel is race-free.

``finish_kernel`` (over worlds) advances the step counter and sets ``world_done``.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from cpsim.kernels.common import (
    COLLISION,
    GOAL,
    IDM,
    KERNEL_MODULE,
    LAST_LOG_STEP,
    OFFROAD,
    POLICY,
    REPLAY,
    RULE_IGNORE,
    RULE_REMOVE,
    RUNNING,
    STATIC,
    TIMEOUT,
    VEHICLE,
    Params,
    launch,
    launcher,
)
from cpsim.kernels.geometry import (
    box_corner_cs,
    boxes_overlap,
    collision_kind,
    grid_cell,
    kind_at_fault,
    kind_needs_straddle,
    lane_distance,
    lane_query,
    segment_hits_box_cs,
    segments_intersect,
    straddles_divider,
)
from cpsim.kernels.observation import tracked_role
from cpsim.kernels.reward import comfort_violations, write_reward
from cpsim.model_arrays import ModelArrays
from cpsim.state import State, StepScratch


@wp.func
def offroad_test(m: ModelArrays, g: int, p: wp.vec2f, h: float, prev_p: wp.vec2f, prev_h: float,
                 half_len: float, half_wid: float) -> bool:
    """A road edge touches the box at (p, h) or crosses a corner path from (prev_p, prev_h)."""
    return offroad_test_cs(m, g, p, h, wp.vec2f(wp.cos(h), wp.sin(h)), prev_p, prev_h,
                           wp.vec2f(wp.cos(prev_h), wp.sin(prev_h)), half_len, half_wid)


@wp.func
def offroad_test_cs(m: ModelArrays, g: int, p: wp.vec2f, h: float, cs: wp.vec2f, prev_p: wp.vec2f,
                    prev_h: float, prev_cs: wp.vec2f, half_len: float, half_wid: float) -> bool:
    """:func:`offroad_test` given the (cos, sin) of both headings (the step's ``trig`` and
    ``prev_trig``: no trigonometry per agent)."""
    cell = grid_cell(m, g, p, False)
    hit = bool(False)
    if cell >= 0:
        first = m.edge_start[cell]
        last = m.edge_start[cell + 1]
        if last > first:
            c = cs[0]
            s = cs[1]
            pc = prev_cs[0]
            ps = prev_cs[1]
            moved = wp.length(p - prev_p) > 0.0 or h != prev_h
            a0 = box_corner_cs(prev_p, pc, ps, half_len, half_wid, 0)
            a1 = box_corner_cs(prev_p, pc, ps, half_len, half_wid, 1)
            a2 = box_corner_cs(prev_p, pc, ps, half_len, half_wid, 2)
            a3 = box_corner_cs(prev_p, pc, ps, half_len, half_wid, 3)
            b0 = box_corner_cs(p, c, s, half_len, half_wid, 0)
            b1 = box_corner_cs(p, c, s, half_len, half_wid, 1)
            b2 = box_corner_cs(p, c, s, half_len, half_wid, 2)
            b3 = box_corner_cs(p, c, s, half_len, half_wid, 3)
            # axis-aligned bounds of both boxes: a cheap reject before the exact tests
            lo = wp.min(wp.min(wp.min(a0, a1), wp.min(a2, a3)), wp.min(wp.min(b0, b1), wp.min(b2, b3)))
            hi = wp.max(wp.max(wp.max(a0, a1), wp.max(a2, a3)), wp.max(wp.max(b0, b1), wp.max(b2, b3)))
            for q in range(first, last):
                sid = m.edge_items[q]
                ea = m.seg_a[sid]
                eb = m.seg_b[sid]
                if wp.max(ea[0], eb[0]) < lo[0] or wp.min(ea[0], eb[0]) > hi[0] \
                        or wp.max(ea[1], eb[1]) < lo[1] or wp.min(ea[1], eb[1]) > hi[1]:
                    continue
                if segment_hits_box_cs(ea, eb, p, c, s, half_len, half_wid):
                    hit = True
                elif moved:
                    if segments_intersect(a0, b0, ea, eb) or segments_intersect(a1, b1, ea, eb) \
                            or segments_intersect(a2, b2, ea, eb) or segments_intersect(a3, b3, ea, eb):
                        hit = True
                if hit:
                    break
    return hit


@wp.func
def replay_pose(m: ModelArrays, row: int, t: int, p: wp.vec2f, h: float, prev_p: wp.vec2f, prev_h: float) -> bool:
    """Whether (prev_p, prev_h) -> (p, h) is exactly log row ``row``'s move from step t-1 to t."""
    q = m.log_xy[row, t]
    r = m.log_xy[row, t - 1]
    return (p[0] == q[0] and p[1] == q[1] and h == m.log_heading[row, t] and prev_p[0] == r[0]
            and prev_p[1] == r[1] and prev_h == m.log_heading[row, t - 1])


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def replay_offroad_kernel(model: ModelArrays, box_scale: float, out: wp.array2d(dtype=wp.bool)):
    """out[row, t] = the off-road test of ``agent_events`` for a vehicle moving from log step
    t-1 to log step t of row ``row`` (False at t = 0 and for other agent types); over (L, T).
    Built once per Model: replayed agents (most of a WOMD scene) then skip the test.

    Reads: -
    Writes: -
    """
    row, t = wp.tid()
    hit = bool(False)
    if t > 0 and model.agent_type[row] == VEHICLE:
        p = model.log_xy[row, t]
        h = model.log_heading[row, t]
        prev_p = model.log_xy[row, t - 1]
        prev_h = model.log_heading[row, t - 1]
        size = model.size[row]
        L = size[0] * box_scale
        Wd = size[1] * box_scale
        hit = offroad_test_cs(model, model.agent_scenario[row], p, h, wp.vec2f(wp.cos(h), wp.sin(h)), prev_p, prev_h,
                              wp.vec2f(wp.cos(prev_h), wp.sin(prev_h)), 0.5 * L, 0.5 * Wd)
    out[row, t] = hit


@launcher(replay_offroad_kernel)
def launch_replay_offroad(model: ModelArrays, box_scale: float, out: wp.array, *, dim: Any, device: Any = None,
                          record: bool = False) -> Any:
    """Launch :func:`replay_offroad_kernel` over ``dim`` = (L, T). Output: ``out`` (L, T) bool.

    Writes: -
    """
    return launch(replay_offroad_kernel, launch_replay_offroad.kernels, dim, [model, float(box_scale)], [out],
                  device=device, record=record)


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def events_kernel(state: State, scratch: StepScratch, model: ModelArrays, params: Params, track_all: int,
                  trig: wp.array2d(dtype=wp.vec2f), prev_trig: wp.array2d(dtype=wp.vec2f),
                  present_idx: wp.array2d(dtype=wp.int32), tracked_idx: wp.array2d(dtype=wp.int32),
                  roster_n: wp.array2d(dtype=wp.int32), radius: wp.array2d(dtype=wp.float32)):
    """:func:`agent_events` over (W, A), one thread per agent (CUDA).

    Reads: accel, agent_index, agent_row, agent_type, aligned_steps, comfort_violations, conditions, controller,
        finished, first_collision_step, first_offroad_step, goal, goal_step, heading, jerk, lat_accel,
        lat_jerk, lateral_offset_sum, outcome, pos, pos_hist, prev_heading, prev_pos, prev_vel, scenario, size,
        speed, step_count, steps_alive, task_agent, scratch.present
    Writes: aligned_steps, alive, at_fault, collision_partner, comfort_violations, controller, done, finished,
        first_collision_step, first_offroad_step, goal_step, has_lane, lane_err, lane_offset,
        lateral_offset_sum, outcome, reward, reward_raw, reward_w, steps_alive, terminated, truncated
    """
    w, a = wp.tid()
    agent_events(state, scratch, model, params, track_all, trig, prev_trig, present_idx, tracked_idx, roster_n,
                 radius, w, a)


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def events_world_kernel(state: State, scratch: StepScratch, model: ModelArrays, params: Params, track_all: int,
                        trig: wp.array2d(dtype=wp.vec2f), prev_trig: wp.array2d(dtype=wp.vec2f),
                        present_idx: wp.array2d(dtype=wp.int32), tracked_idx: wp.array2d(dtype=wp.int32),
                        roster_n: wp.array2d(dtype=wp.int32), radius: wp.array2d(dtype=wp.float32)):
    """:func:`agent_events` over W, one thread per world looping over its slots (CPU: a CPU
    thread copies the kernel's State / ModelArrays arguments on entry, about 60 ns, so one
    entry per world instead of per slot; same order, same results as :func:`events_kernel`).

    Reads: accel, agent_index, agent_row, agent_type, aligned_steps, comfort_violations, conditions, controller,
        finished, first_collision_step, first_offroad_step, goal, goal_step, heading, jerk, lat_accel,
        lat_jerk, lateral_offset_sum, outcome, pos, pos_hist, prev_heading, prev_pos, prev_vel, scenario, size,
        speed, step_count, steps_alive, task_agent, scratch.present
    Writes: aligned_steps, alive, at_fault, collision_partner, comfort_violations, controller, done, finished,
        first_collision_step, first_offroad_step, goal_step, has_lane, lane_err, lane_offset,
        lateral_offset_sum, outcome, reward, reward_raw, reward_w, steps_alive, terminated, truncated
    """
    w = wp.tid()
    for a in range(scratch.present.shape[1]):
        agent_events(state, scratch, model, params, track_all, trig, prev_trig, present_idx, tracked_idx, roster_n,
                     radius, w, a)


@launcher(events_kernel, events_world_kernel)
def launch_events(state: State, scratch: StepScratch, model: ModelArrays, params: Params, track_all: int,
                  trig: wp.array, prev_trig: wp.array, present_idx: wp.array, tracked_idx: wp.array,
                  roster_n: wp.array, radius: wp.array, *, dim: Any, device: Any = None, record: bool = False,
                  kernel: wp.Kernel = events_kernel) -> Any:
    """Launch the events of a step (``kernel``: :func:`events_kernel` over (W, A) or
    :func:`events_world_kernel` over W); the arrays from ``prepare_kernel`` are read only.

    Writes: aligned_steps, alive, at_fault, collision_partner, comfort_violations, controller, done, finished,
        first_collision_step, first_offroad_step, goal_step, has_lane, lane_err, lane_offset,
        lateral_offset_sum, outcome, reward, reward_raw, reward_w, steps_alive, terminated, truncated
    """
    return launch(kernel, launch_events.kernels, dim,
                  [state, scratch, model, params, int(track_all), trig, prev_trig, present_idx, tracked_idx,
                   roster_n, radius], device=device, record=record)


@wp.func(inline=True)
def agent_events(state: State, scratch: StepScratch, model: ModelArrays, params: Params, track_all: int,
                 trig: wp.array2d(dtype=wp.vec2f), prev_trig: wp.array2d(dtype=wp.vec2f),
                 present_idx: wp.array2d(dtype=wp.int32), tracked_idx: wp.array2d(dtype=wp.int32),
                 roster_n: wp.array2d(dtype=wp.int32), radius: wp.array2d(dtype=wp.float32), w: int, a: int):
    """Collisions, off-road, goal, lanes, outcome, metrics, reward, removal, timeout of agent
    (w, a) (the body of ``events_kernel`` / ``events_world_kernel``).

    ``trig`` / ``prev_trig`` (heading (cos, sin) now and before the motion), the roster
    (``present_idx``, ``tracked_idx``, ``roster_n``) and the scaled box half-diagonals
    (``radius``) come from :func:`cpsim.kernels.observation.prepare_kernel`, launched just
    before. A REPLAY agent on its logged poses takes its off-road result from the model's
    precomputed ``log_offroad`` table (the same test on the same inputs).

    Tracked agents (:func:`cpsim.kernels.observation.tracked_role`: POLICY, IDM, task agents,
    agents stopped by the ``stop`` rule, slot 0) get everything below. Scenery (REPLAY /
    STATIC agents without a task) is only tested for collisions with tracked agents (so a
    collision of the ego or a co-player with a parked or replayed car is recorded on both
    sides, partner and fault included), off-road and timeout (agents without a task have no goal): no lane query, no metrics
    accumulators (they stay 0), reward 0. Nothing reads those for scenery, and scenery
    outnumbers the tracked agents about 5 to 1 on WOMD.
    """
    if state.step_count[w] >= params.episode_steps or not scratch.present[w, a]:
        if state.agent_index[w, a] >= 0:  # empty slots keep the zeros written at reset
            state.reward[w, a] = 0.0
            for k in range(state.reward_raw.shape[2]):
                state.reward_raw[w, a, k] = 0.0
                state.reward_w[w, a, k] = 0.0
        return
    tracked = tracked_role(state.controller[w, a], state.task_agent[w, a], state.finished[w, a], a,
                           params.observe_all, track_all)
    t1 = state.step_count[w] + 1
    g = state.scenario[w]
    p = state.pos[w, a]
    h = state.heading[w, a]
    v = state.speed[w, a]
    size = state.size[w, a]
    scale = params.box_scale
    L = size[0] * scale
    Wd = size[1] * scale
    r_i = 0.5 * wp.sqrt(L * L + Wd * Wd)
    my_type = state.agent_type[w, a]
    # ---------------------------------------------------------------- collisions
    collided = bool(False)
    partner = int(-1)
    best = float(1.0e30)
    if my_type == VEHICLE or params.collide_types != 0:
        # tracked: every present agent; scenery: the present tracked ones (both in slot order)
        num = roster_n[w, 1]
        if tracked:
            num = roster_n[w, 0]
        for k in range(num):
            j = tracked_idx[w, k]
            if tracked:
                j = present_idx[w, k]
            if j == a:
                continue
            if state.agent_type[w, j] != VEHICLE and params.collide_types == 0:
                continue
            d = state.pos[w, j] - p
            r_j = radius[w, j]
            d2 = wp.dot(d, d)
            if d2 > (r_i + r_j) * (r_i + r_j):
                continue
            sj = state.size[w, j]
            lj = sj[0] * scale
            wj = sj[1] * scale
            if boxes_overlap(p, h, L, Wd, state.pos[w, j], state.heading[w, j], lj, wj):
                collided = bool(True)
                if d2 < best:
                    best = d2
                    partner = j
    # ---------------------------------------------------------------- off-road
    offroad = bool(False)
    if my_type == VEHICLE:
        prev_p = state.prev_pos[w, a]
        prev_h = state.prev_heading[w, a]
        row = state.agent_row[w, a]
        if state.controller[w, a] == REPLAY and t1 <= LAST_LOG_STEP and replay_pose(model, row, t1, p, h, prev_p,
                                                                                    prev_h):
            offroad = model.log_offroad[row, t1]
        else:
            offroad = offroad_test_cs(model, g, p, h, trig[w, a], prev_p, prev_h, prev_trig[w, a], 0.5 * L, 0.5 * Wd)
    # ---------------------------------------------------------------- goal
    gr = state.conditions[w, a, 0]
    gs = state.conditions[w, a, 1]
    if params.goal_fixed != 0:  # one goal test for everyone (SimConfig.goal_criterion)
        gr = params.goal_radius
        gs = params.goal_speed
    # Only task agents have a goal: a vehicle parked at its goal (no task, start within 2 m of
    # its goal) that the evaluator hands to a traffic regime would otherwise "arrive" on its
    # first step and leave the scene.
    reached = state.task_agent[w, a] and wp.length(p - state.goal[w, a]) < gr and wp.abs(v) <= gs
    goal_now = reached and state.goal_step[w, a] < 0
    # ---------------------------------------------------------------- lane (tracked only)
    has_lane = bool(False)
    err = float(0.0)
    offset = float(0.0)
    if tracked:
        sid, ld, q_offset, q_err = lane_query(model, g, p, h, params.lane_radius)
        if sid >= 0:
            has_lane = bool(True)
            err = q_err
            offset = q_offset
    state.has_lane[w, a] = has_lane
    state.lane_err[w, a] = err
    state.lane_offset[w, a] = offset
    # ---------------------------------------------------------------- metrics (tracked only)
    violations = int(0)
    if tracked:
        violations = comfort_violations(state.accel[w, a], state.lat_accel[w, a], state.jerk[w, a],
                                        state.lat_jerk[w, a])
        state.steps_alive[w, a] = state.steps_alive[w, a] + 1
        state.comfort_violations[w, a] = state.comfort_violations[w, a] + violations
        if has_lane and wp.abs(err) < params.align_rad:
            state.aligned_steps[w, a] = state.aligned_steps[w, a] + 1
        if has_lane:
            state.lateral_offset_sum[w, a] = state.lateral_offset_sum[w, a] + wp.abs(offset)
        else:
            # the true distance to the nearest lane centreline (beyond lane_radius)
            state.lateral_offset_sum[w, a] = state.lateral_offset_sum[w, a] + lane_distance(model, g, p)
    if collided:
        # BehaviorBench's at-fault rules, from the state one step before contact
        j = partner
        ph = state.prev_heading[w, a]
        kind = collision_kind(state.prev_pos[w, a], ph, state.prev_vel[w, a], state.prev_pos[w, j],
                              state.prev_vel[w, j], state.agent_type[w, j] != VEHICLE)
        straddled = bool(False)
        if kind_needs_straddle(kind):  # rear / lateral: fault only when straddling
            nh = state.pos_hist.shape[2]
            newest = state.step_count[w] % nh
            straddled = straddles_divider(model, g, state.pos_hist[w, a, (newest + 1) % nh],
                                          state.pos_hist[w, a, (newest + 2) % nh],
                                          state.pos_hist[w, a, (newest + 3) % nh],
                                          state.pos_hist[w, a, newest], ph, Wd, params.lane_radius)
        if kind_at_fault(kind, straddled):
            state.at_fault[w, a] = True
        if state.first_collision_step[w, a] < 0:
            state.first_collision_step[w, a] = t1
            state.collision_partner[w, a] = partner
    if offroad and state.first_offroad_step[w, a] < 0:
        state.first_offroad_step[w, a] = t1
    if goal_now:
        state.goal_step[w, a] = t1
    # ---------------------------------------------------------------- outcome (sticky)
    if state.outcome[w, a] == RUNNING:
        if collided:
            state.outcome[w, a] = COLLISION
        elif offroad:
            state.outcome[w, a] = OFFROAD
        elif goal_now:
            state.outcome[w, a] = GOAL
    # ---------------------------------------------------------------- reward (tracked only)
    if tracked:
        state.reward[w, a] = write_reward(state.conditions, state.reward_raw, state.reward_w, w, a,
                                          goal_now, collided, offroad, violations, has_lane, err, offset, v,
                                          state.accel[w, a], params.dt)
    else:
        state.reward[w, a] = 0.0
        for k in range(state.reward_raw.shape[2]):
            state.reward_raw[w, a, k] = 0.0
            state.reward_w[w, a, k] = 0.0
    # ---------------------------------------------------------------- removal
    ctrl = state.controller[w, a]
    rule = RULE_IGNORE
    if collided:
        rule = wp.min(rule, params.on_collision)
    if offroad:
        rule = wp.min(rule, params.on_offroad)
    if goal_now:
        rule = wp.min(rule, params.on_goal)
    still_alive = bool(True)
    if (ctrl == POLICY or ctrl == IDM) and rule != RULE_IGNORE:
        state.finished[w, a] = True
        state.done[w, a] = True
        state.terminated[w, a] = True
        if rule == RULE_REMOVE:
            state.alive[w, a] = False
            still_alive = bool(False)
        else:
            state.controller[w, a] = STATIC
    # ---------------------------------------------------------------- timeout
    if t1 >= params.episode_steps and still_alive and not state.finished[w, a]:
        state.finished[w, a] = True
        state.done[w, a] = True
        state.truncated[w, a] = True
        if state.outcome[w, a] == RUNNING:
            state.outcome[w, a] = TIMEOUT


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def finish_kernel(state: State, params: Params, worlds: wp.array(dtype=wp.int32), advance: int):
    """Advance the step counter (when ``advance``) and set world_done (over len(worlds)).

    Reads: alive, controller, step_count
    Writes: step_count, world_done
    """
    i = wp.tid()
    w = worlds[i]
    if state.step_count[w] >= params.episode_steps:
        state.world_done[w] = True
        return
    t = state.step_count[w] + advance
    state.step_count[w] = t
    any_policy = bool(False)
    num = state.alive.shape[1]
    for a in range(num):
        if state.alive[w, a] and state.controller[w, a] == POLICY:
            any_policy = bool(True)
    state.world_done[w] = t >= params.episode_steps or not any_policy


@launcher(finish_kernel)
def launch_finish(state: State, params: Params, worlds: wp.array, advance: int, *, dim: Any, device: Any = None,
                  record: bool = False) -> Any:
    """Launch :func:`finish_kernel` over ``dim`` = len(worlds); ``worlds`` is read only.

    Writes: step_count, world_done
    """
    return launch(finish_kernel, launch_finish.kernels, dim, [state, params, worlds, int(advance)], device=device,
                  record=record)


__all__ = ["events_kernel", "events_world_kernel", "agent_events", "finish_kernel", "offroad_test",
           "offroad_test_cs", "replay_offroad_kernel", "replay_pose", "launch_events", "launch_finish",
           "launch_replay_offroad"]
