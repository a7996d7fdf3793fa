"""Observation kernel: ego-frame features, condition, K nearest partners, M road segments.

Layout and normalisation are documented in :mod:`cpsim.observation`. Cost per agent is
O(A + K) for partners (one pass with an insertion sort into a K-slot scratch list) and
O(M) for the road (the grid cell's precomputed candidate list).

Also here: ``prepare_kernel``, the per-world pass of a step between the motion and the
events (heading (cos, sin) of every present agent, and the roster of present and tracked
slots the events kernel iterates), and :func:`tracked_role`, which agents get every event
and metric (see :mod:`cpsim.kernels.metrics`).
"""

from __future__ import annotations

import inspect
from typing import Any

import warp as wp

from cpsim.conditions import TRAIN_HIGH, TRAIN_LOW
from cpsim.kernels.common import IDM, KERNEL_MODULE, POLICY, STATIC, VEHICLE, Params, launch, launcher
from cpsim.kernels.geometry import grid_cell, to_local
from cpsim.model_arrays import ModelArrays
from cpsim.state import State, StepScratch

_COND_LOW = wp.constant(wp.types.vector(10, wp.float32)(*TRAIN_LOW.tolist()))
_COND_SPAN = wp.constant(wp.types.vector(10, wp.float32)(*(TRAIN_HIGH - TRAIN_LOW).tolist()))
ROAD_LANE = wp.constant(0)
ROAD_EDGE = wp.constant(2)


@wp.func
def tracked_role(ctrl: int, task: bool, finished: bool, a: int, observe_all: int, track_all: int) -> bool:
    """Whether the agent in slot ``a`` is *tracked*: it gets every event and metric of a step
    (collisions with everyone, lane, metrics accumulators, reward). Tracked are POLICY and IDM
    agents, agents the ``stop`` rule turned STATIC (STATIC and ``finished``), task agents
    (controllable at reset, whatever their controller now), slot 0 (the ego) and, with
    ``observe_all`` or ``track_all``, everyone. The others are *scenery* (REPLAY / STATIC
    agents without a task): see ``events_kernel``."""
    return (ctrl == POLICY or ctrl == IDM or task or a == 0 or (ctrl == STATIC and finished)
            or observe_all != 0 or track_all != 0)


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def prepare_kernel(state: State, scratch: StepScratch, params: Params, track_all: int, trig: wp.array2d(dtype=wp.vec2f),
                   prev_trig: wp.array2d(dtype=wp.vec2f), present_idx: wp.array2d(dtype=wp.int32),
                   tracked_idx: wp.array2d(dtype=wp.int32), roster_n: wp.array2d(dtype=wp.int32),
                   radius: wp.array2d(dtype=wp.float32)):
    """Per world (over W), after the motion: for every present agent, ``prev_trig`` <- ``trig``
    (the (cos, sin) of its heading before the motion), ``trig`` <- (cos, sin) of its heading
    now and ``radius`` <- the half-diagonal of its box scaled by ``box_scale`` (the collision
    pre-filter); ``present_idx[w, :n]`` lists the present slots and ``tracked_idx[w, :m]`` the
    present tracked ones (:func:`tracked_role`), both in slot order; ``roster_n[w]`` = (n, m).

    Reads: controller, finished, heading, size, task_agent, scratch.present
    Writes: -
    """
    w = wp.tid()
    n = int(0)
    m = int(0)
    for a in range(scratch.present.shape[1]):
        if scratch.present[w, a]:
            prev_trig[w, a] = trig[w, a]
            h = state.heading[w, a]
            trig[w, a] = wp.vec2f(wp.cos(h), wp.sin(h))
            size = state.size[w, a]
            length = size[0] * params.box_scale
            width = size[1] * params.box_scale
            radius[w, a] = 0.5 * wp.sqrt(length * length + width * width)
            present_idx[w, n] = a
            n += 1
            if tracked_role(state.controller[w, a], state.task_agent[w, a], state.finished[w, a], a,
                            params.observe_all, track_all):
                tracked_idx[w, m] = a
                m += 1
    roster_n[w, 0] = n
    roster_n[w, 1] = m


@launcher(prepare_kernel)
def launch_prepare(state: State, scratch: StepScratch, params: Params, track_all: int, trig: wp.array,
                   prev_trig: wp.array, present_idx: wp.array, tracked_idx: wp.array, roster_n: wp.array,
                   radius: wp.array, *, dim: Any, device: Any = None, record: bool = False) -> Any:
    """Launch :func:`prepare_kernel` over ``dim`` = W. Outputs: ``trig`` (also read),
    ``prev_trig``, ``present_idx``, ``tracked_idx``, ``roster_n``, ``radius``.

    Writes: -
    """
    return launch(prepare_kernel, launch_prepare.kernels, dim, [state, scratch, params, track_all],
                  [trig, prev_trig, present_idx, tracked_idx, roster_n, radius], device=device, record=record)


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def heading_trig_kernel(state: State, worlds: wp.array(dtype=wp.int32), trig: wp.array2d(dtype=wp.vec2f)):
    """trig[w, a] = (cos, sin) of every heading (a pre-pass: partners reuse them, over (n, A)).

    Reads: heading
    Writes: -
    """
    i, a = wp.tid()
    w = worlds[i]
    h = state.heading[w, a]
    trig[w, a] = wp.vec2f(wp.cos(h), wp.sin(h))


@launcher(heading_trig_kernel)
def launch_heading_trig(state: State, worlds: wp.array, trig: wp.array, *, dim: Any, device: Any = None,
                        record: bool = False) -> Any:
    """Launch :func:`heading_trig_kernel` over ``dim`` = (len(worlds), A). Output: ``trig``.

    Writes: -
    """
    return launch(heading_trig_kernel, launch_heading_trig.kernels, dim, [state, worlds], [trig],
                  device=device, record=record)


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def observation_kernel(state: State, model: ModelArrays, params: Params,
                       worlds: wp.array(dtype=wp.int32), trig: wp.array2d(dtype=wp.vec2f), force: int,
                       obs: wp.array3d(dtype=wp.float32), sel_idx: wp.array3d(dtype=wp.int32),
                       sel_d2: wp.array3d(dtype=wp.float32), obs_clear: wp.array2d(dtype=wp.bool),
                       filled: wp.array3d(dtype=wp.int32)):
    """:func:`observe_agent` for the worlds listed in ``worlds``, over (len(worlds), A): one
    thread per agent (CUDA).

    Reads: accel, agent_type, alive, conditions, controller, first_collision_step, first_offroad_step, goal,
        has_lane, lane_err, lane_offset, lat_accel, pos, scenario, size, speed, steer, step_count,
        task_agent, vel
    Writes: -
    """
    i, a = wp.tid()
    observe_agent(state, model, params, worlds[i], a, obs, sel_idx, sel_d2, obs_clear, filled, trig, force)


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def observation_world_kernel(state: State, model: ModelArrays, params: Params,
                             worlds: wp.array(dtype=wp.int32), trig: wp.array2d(dtype=wp.vec2f), force: int,
                             obs: wp.array3d(dtype=wp.float32), sel_idx: wp.array3d(dtype=wp.int32),
                             sel_d2: wp.array3d(dtype=wp.float32), obs_clear: wp.array2d(dtype=wp.bool),
                             filled: wp.array3d(dtype=wp.int32)):
    """:func:`observe_agent` for the worlds listed in ``worlds``, over len(worlds): one thread
    per world looping over its slots (CPU: fewer copies of the State / ModelArrays arguments,
    which a CPU thread makes on entry; same order and results as ``observation_kernel``).

    Reads: accel, agent_type, alive, conditions, controller, first_collision_step, first_offroad_step, goal,
        has_lane, lane_err, lane_offset, lat_accel, pos, scenario, size, speed, steer, step_count,
        task_agent, vel
    Writes: -
    """
    i = wp.tid()
    w = worlds[i]
    for a in range(obs.shape[1]):
        observe_agent(state, model, params, w, a, obs, sel_idx, sel_d2, obs_clear, filled, trig, force)


@launcher(observation_kernel, observation_world_kernel)
def launch_observation(state: State, model: ModelArrays, params: Params, worlds: wp.array, trig: wp.array,
                       force: int, obs: wp.array, sel_idx: wp.array, sel_d2: wp.array, obs_clear: wp.array,
                       filled: wp.array, *, dim: Any, device: Any = None, record: bool = False,
                       kernel: wp.Kernel = observation_kernel) -> Any:
    """Launch the observation of the worlds listed in ``worlds`` (``kernel``:
    :func:`observation_kernel` over (len(worlds), A) or :func:`observation_world_kernel` over
    len(worlds)); ``trig`` and ``force`` are read only (a recorded launch changes ``force``
    with ``set_param_at_index(OBS_FORCE_ARG, ...)``). Outputs: ``obs``, ``sel_idx``,
    ``sel_d2``, ``obs_clear``, ``filled``.

    Writes: -
    """
    return launch(kernel, launch_observation.kernels, dim, [state, model, params, worlds, trig, int(force)],
                  [obs, sel_idx, sel_d2, obs_clear, filled], device=device, record=record)


#: Index of ``force`` among the observation kernels' parameters (for ``set_param_at_index``).
OBS_FORCE_ARG = list(inspect.signature(observation_kernel.func).parameters).index("force")
assert OBS_FORCE_ARG == list(inspect.signature(observation_world_kernel.func).parameters).index("force")


@wp.func(inline=True)
def observe_agent(state: State, model: ModelArrays, params: Params, w: int, a: int,
                  obs: wp.array3d(dtype=wp.float32), sel_idx: wp.array3d(dtype=wp.int32),
                  sel_d2: wp.array3d(dtype=wp.float32), obs_clear: wp.array2d(dtype=wp.bool),
                  filled: wp.array3d(dtype=wp.int32), trig: wp.array2d(dtype=wp.vec2f), force: int):
    """Write obs[w, a, :]: :func:`ego_features`, :func:`condition_features`,
    :func:`partner_features` of the :func:`nearest_partners`, :func:`road_features`.

    Observed are alive agents driven by the policy or holding a task (``task_agent``), or
    every alive agent with ``observe_all``; the others observe zeros; ``obs_clear`` remembers rows already zeroed so empty and
    removed slots cost nothing on later steps, and ``filled[w, a]`` = (partners, road
    segments, grid cell) written last time, so only entries that were filled before are
    zeroed again and constant road features are kept while the agent stays in its cell.
    ``force`` rewrites whole rows (after a restore or an external state edit).
    """
    D = params.obs_dim
    observed = state.alive[w, a] and (params.observe_all != 0 or state.controller[w, a] == POLICY
                                      or state.task_agent[w, a])
    if not observed:
        if force != 0 or not obs_clear[w, a]:
            for k in range(D):
                obs[w, a, k] = 0.0
            obs_clear[w, a] = True
        return
    prev_partners = params.num_partners
    prev_road = params.num_road
    was_clear = obs_clear[w, a]
    if force == 0:
        if was_clear:
            prev_partners = 0
            prev_road = 0
        else:
            prev_partners = filled[w, a, 0]
            prev_road = filled[w, a, 1]
    obs_clear[w, a] = False
    p = state.pos[w, a]
    cs = trig[w, a]
    c = cs[0]
    s = cs[1]
    ego_features(state, params, w, a, p, c, s, obs)
    condition_features(state, params, w, a, obs)
    n = nearest_partners(state, model, params, w, a, p, sel_idx, sel_d2)
    partner_features(state, params, w, a, p, c, s, n, prev_partners, obs, sel_idx, trig)
    filled[w, a, 0] = n
    same_cell = force == 0 and not was_clear
    mcount = road_features(state, model, params, w, a, p, c, s, same_cell, prev_road, obs, filled)
    filled[w, a, 1] = mcount


@wp.func(inline=True)
def ego_features(state: State, params: Params, w: int, a: int, p: wp.vec2f, c: float, s: float,
                 obs: wp.array3d(dtype=wp.float32)):
    """obs[w, a, 0:17], the ego features of :data:`cpsim.observation.EGO_FEATURE_NAMES`: speed
    / 20 m/s, accel / 5 m/s^2, lateral accel / 4 m/s^2, steer / 0.55 rad, length / 10 m,
    width / 5 m, goal offset in the ego frame / 100 m (x, y clamped to [-1, 1]), goal
    direction (unit x, y), goal distance / 100 m (<= 1), lane heading error / pi, lane
    offset / lane_radius, has-lane flag, collided and off-road flags, time left (1 at reset,
    0 at the episode's end). ``p`` (m) and (``c``, ``s``) = (cos, sin) of the heading are the
    ego pose."""
    size = state.size[w, a]
    obs[w, a, 0] = state.speed[w, a] / 20.0
    obs[w, a, 1] = state.accel[w, a] / 5.0
    obs[w, a, 2] = state.lat_accel[w, a] / 4.0
    obs[w, a, 3] = state.steer[w, a] / 0.55
    obs[w, a, 4] = size[0] / 10.0
    obs[w, a, 5] = size[1] / 5.0
    g_local = to_local(state.goal[w, a] - p, c, s)
    g_dist = wp.length(g_local)
    obs[w, a, 6] = wp.clamp(g_local[0] / 100.0, -1.0, 1.0)
    obs[w, a, 7] = wp.clamp(g_local[1] / 100.0, -1.0, 1.0)
    if g_dist > 1.0e-6:
        obs[w, a, 8] = g_local[0] / g_dist
        obs[w, a, 9] = g_local[1] / g_dist
    else:
        obs[w, a, 8] = 0.0
        obs[w, a, 9] = 0.0
    obs[w, a, 10] = wp.min(g_dist / 100.0, 1.0)
    if state.has_lane[w, a]:
        obs[w, a, 11] = state.lane_err[w, a] / 3.14159265
        obs[w, a, 12] = state.lane_offset[w, a] / params.lane_radius
        obs[w, a, 13] = 1.0
    else:
        obs[w, a, 11] = 0.0
        obs[w, a, 12] = 0.0
        obs[w, a, 13] = 0.0
    collided = float(0.0)
    if state.first_collision_step[w, a] >= 0:
        collided = 1.0
    offroad = float(0.0)
    if state.first_offroad_step[w, a] >= 0:
        offroad = 1.0
    obs[w, a, 14] = collided
    obs[w, a, 15] = offroad
    obs[w, a, 16] = 1.0 - float(state.step_count[w]) / float(params.episode_steps)


@wp.func(inline=True)
def condition_features(state: State, params: Params, w: int, a: int, obs: wp.array3d(dtype=wp.float32)):
    """obs[w, a, obs_condition:+10]: the agent's 10 condition fields mapped linearly from the
    training range [TRAIN_LOW, TRAIN_HIGH] (:mod:`cpsim.conditions`) to [-1, 1]."""
    oc = params.obs_condition
    for f in range(10):
        obs[w, a, oc + f] = 2.0 * (state.conditions[w, a, f] - _COND_LOW[f]) / _COND_SPAN[f] - 1.0


@wp.func(inline=True)
def nearest_partners(state: State, model: ModelArrays, params: Params, w: int, a: int, p: wp.vec2f,
                     sel_idx: wp.array3d(dtype=wp.int32), sel_d2: wp.array3d(dtype=wp.float32)) -> int:
    """The ``n`` <= num_partners (K) nearest other alive agents within ``partner_radius`` of
    ``p`` (m): their slots in ``sel_idx[w, a, :n]`` and squared distances (m^2) in
    ``sel_d2[w, a, :n]``, nearest first (one pass over the slots with an insertion sort into
    the K-slot scratch list; ties keep slot order). Returns ``n``."""
    K = params.num_partners
    n = int(0)
    if K > 0:
        R2 = params.partner_radius * params.partner_radius
        # a reset fills slots 0 .. slot_count - 1; the slots after them stay empty
        num = wp.min(state.alive.shape[1], model.slot_count[state.scenario[w]])
        for j in range(num):
            if j == a or not state.alive[w, j]:
                continue
            rel = state.pos[w, j] - p
            d2 = wp.dot(rel, rel)
            if d2 > R2:
                continue
            if n == K:
                if d2 >= sel_d2[w, a, K - 1]:
                    continue
            m = n
            if n == K:
                m = K - 1
            while m > 0 and sel_d2[w, a, m - 1] > d2:
                sel_d2[w, a, m] = sel_d2[w, a, m - 1]
                sel_idx[w, a, m] = sel_idx[w, a, m - 1]
                m -= 1
            sel_d2[w, a, m] = d2
            sel_idx[w, a, m] = j
            if n < K:
                n += 1
    return n


@wp.func(inline=True)
def partner_features(state: State, params: Params, w: int, a: int, p: wp.vec2f, c: float, s: float, n: int,
                     prev_partners: int, obs: wp.array3d(dtype=wp.float32), sel_idx: wp.array3d(dtype=wp.int32),
                     trig: wp.array2d(dtype=wp.vec2f)):
    """obs[w, a, obs_partners + k * partner_features:+10] for the ``n`` selected partners
    ``sel_idx[w, a, k]``, in the ego frame of pose (``p`` m, heading (cos, sin) = (``c``,
    ``s``)): relative position / partner_radius, relative heading (cos, sin), relative
    velocity / 20 m/s, length / 10 m, width / 5 m, vulnerable-road-user flag, presence 1;
    the entries of partners ``n .. prev_partners - 1`` (filled last time) are zeroed."""
    PF = params.partner_features
    op = params.obs_partners
    vel = state.vel[w, a]
    inv_r = 1.0 / params.partner_radius
    for k in range(n):
        base = op + k * PF
        j = sel_idx[w, a, k]
        rel = to_local(state.pos[w, j] - p, c, s)
        cj = trig[w, j]
        rv = to_local(state.vel[w, j] - vel, c, s)
        sz = state.size[w, j]
        obs[w, a, base + 0] = rel[0] * inv_r
        obs[w, a, base + 1] = rel[1] * inv_r
        obs[w, a, base + 2] = cj[0] * c + cj[1] * s  # cos(h_j - h)
        obs[w, a, base + 3] = cj[1] * c - cj[0] * s  # sin(h_j - h)
        obs[w, a, base + 4] = rv[0] / 20.0
        obs[w, a, base + 5] = rv[1] / 20.0
        obs[w, a, base + 6] = sz[0] / 10.0
        obs[w, a, base + 7] = sz[1] / 5.0
        vru = float(0.0)
        if state.agent_type[w, j] != VEHICLE:
            vru = 1.0
        obs[w, a, base + 8] = vru
        obs[w, a, base + 9] = 1.0
    for k in range(n * PF, prev_partners * PF):  # entries filled last time, empty now
        obs[w, a, op + k] = 0.0


@wp.func(inline=True)
def road_features(state: State, model: ModelArrays, params: Params, w: int, a: int, p: wp.vec2f, c: float,
                  s: float, keep_constants: bool, prev_road: int, obs: wp.array3d(dtype=wp.float32),
                  filled: wp.array3d(dtype=wp.int32)) -> int:
    """obs[w, a, obs_road + q * road_features:+8] for the up to num_road (M) candidate
    segments of the grid cell holding ``p`` (m), in the ego frame (heading (cos, sin) =
    (``c``, ``s``)): midpoint / road_radius, direction (unit x, y), length /
    road_max_segment, lane and road-edge flags, presence 1. ``keep_constants``: the row was
    filled last step (no force, not cleared), so in the same cell as last time
    (``filled[w, a, 2]``) the constant features are kept. Zeroes the entries of segments
    ``mcount .. prev_road - 1``, records the cell in ``filled[w, a, 2]``; returns ``mcount``.

    The cell's candidate list (nearest midpoints to the cell centre, within road_radius +
    half the cell diagonal) is written in order. While the agent stays in the same cell the
    same segments sit in the same slots, so their constant features (length, type flags,
    presence) are already in place and only the ego-frame pose is rewritten."""
    M = params.num_road
    RF = params.road_features
    orr = params.obs_road
    mcount = int(0)
    if M > 0:
        g = state.scenario[w]
        cell = grid_cell(model, g, p, True)
        same_cell = keep_constants and filled[w, a, 2] == cell
        first = model.obs_start[cell]
        mcount = wp.min(model.obs_start[cell + 1] - first, M)
        inv_rr = 1.0 / params.road_radius
        inv_len = 1.0 / params.road_max_segment
        for q in range(mcount):
            sid = model.obs_items[first + q]
            loc = to_local(model.seg_mid[sid] - p, c, s)
            dl = to_local(model.seg_dir[sid], c, s)
            base = orr + q * RF
            obs[w, a, base + 0] = loc[0] * inv_rr
            obs[w, a, base + 1] = loc[1] * inv_rr
            obs[w, a, base + 2] = dl[0]
            obs[w, a, base + 3] = dl[1]
            if not same_cell:
                t = model.seg_type[sid]
                obs[w, a, base + 4] = model.seg_len[sid] * inv_len
                lane = float(0.0)
                if t == ROAD_LANE:
                    lane = 1.0
                edge = float(0.0)
                if t == ROAD_EDGE:
                    edge = 1.0
                obs[w, a, base + 5] = lane
                obs[w, a, base + 6] = edge
                obs[w, a, base + 7] = 1.0
        filled[w, a, 2] = cell
    for k in range(mcount * RF, prev_road * RF):
        obs[w, a, orr + k] = 0.0
    return mcount


__all__ = ["observation_kernel", "observation_world_kernel", "observe_agent", "ego_features", "condition_features",
           "nearest_partners", "partner_features", "road_features", "heading_trig_kernel", "prepare_kernel",
           "tracked_role", "launch_prepare", "launch_heading_trig", "launch_observation", "OBS_FORCE_ARG"]
