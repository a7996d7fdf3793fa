"""Scripted controllers: IDM along the agent's logged path.

An IDM agent drives along its logged path (its valid logged positions in time order,
continued beyond the last one along the last logged heading) with the Intelligent Driver
Model for speed:

    a = a_max (1 - (v / v0)^4 - (s* / gap)^2),  s* = s0 + max(0, v T + v dv / (2 sqrt(a_max b)))

clipped to [-8, a_max]. Parameters (``SimConfig.idm_*``, BehaviorBench's defaults): v0 = 15 m/s
(``idm_v0``; 0 selects each agent's largest logged speed), jam gap s0 = 1 m, headway T = 1.5 s,
a_max = 1.0 m/s^2, b = 3.0 m/s^2. Agents whose log moves less than 1 m stay put (v0 = 0). The leader is the nearest live agent whose centre lies
within half the two widths + 0.3 m of the path ahead (up to ``idm_lookahead`` m);
gap = arc distance - half the two lengths, dv = v - (leader velocity along the path).
Crossing agents: a moving agent (> 0.5 m/s) off the path whose next 3 s of straight-line
motion crosses the path ahead, and that gets to the crossing point before this agent
would (at max(v, 0.5) m/s), is a stopped obstacle at the crossing point (yielding).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from cpsim.kernels.common import IDM, KERNEL_MODULE, Params, launch, launcher
from cpsim.kernels.geometry import cross2, wrap_angle
from cpsim.model_arrays import ModelArrays
from cpsim.state import State, StepScratch

#: Horizon (s) of the straight-line prediction used for yielding to crossing agents.
CROSSING_HORIZON = 3.0


@wp.func
def path_pose(m: ModelArrays, row: int, s: float, k_hint: int):
    """Pose at arc length s along log row ``row``'s path; returns (pos, heading, segment cursor)."""
    n = m.path_n[row]
    last = wp.max(n - 1, 0)
    pos = m.path_xy[row, last]
    heading = m.path_h[row, last]
    k = wp.max(k_hint, 0)
    if n <= 1 or s >= m.path_s[row, last]:
        ext = s - m.path_s[row, last]
        pos = pos + ext * wp.vec2f(wp.cos(heading), wp.sin(heading))
        k = wp.max(n - 2, 0)
    else:
        while k < n - 2 and m.path_s[row, k + 1] <= s:
            k += 1
        s0 = m.path_s[row, k]
        s1 = m.path_s[row, k + 1]
        f = wp.clamp((s - s0) / wp.max(s1 - s0, 1.0e-6), 0.0, 1.0)
        p0 = m.path_xy[row, k]
        p1 = m.path_xy[row, k + 1]
        pos = p0 + f * (p1 - p0)
        h0 = m.path_h[row, k]
        heading = wrap_angle(h0 + f * wrap_angle(m.path_h[row, k + 1] - h0))
    return pos, heading, k


@wp.func
def _path_segment(m: ModelArrays, row: int, k: int, n: int, s_to: float):
    """Segment k of the path (k = n-1 is the extension, as long as needed to reach s_to).

    Returns (start, end, arc length at start)."""
    last = wp.max(n - 1, 0)
    a = m.path_xy[row, wp.min(k, last)]
    sa = m.path_s[row, wp.min(k, last)]
    b = a
    if k < n - 1:
        b = m.path_xy[row, k + 1]
    else:
        h = m.path_h[row, last]
        b = a + wp.max(s_to - sa, 0.0) * wp.vec2f(wp.cos(h), wp.sin(h))
    return a, b, sa


@wp.func
def path_project(m: ModelArrays, row: int, p: wp.vec2f, k_from: int, s_to: float):
    """Nearest point of the path from segment ``k_from`` to arc ``s_to`` (extension included).

    Returns (distance m, arc length of the nearest point m, unit path direction there)."""
    n = m.path_n[row]
    best_d = float(1.0e9)
    best_s = float(0.0)
    best_dir = wp.vec2f(1.0, 0.0)
    k = wp.max(k_from, 0)
    done = bool(False)
    while not done:
        a, b, sa = _path_segment(m, row, k, n, s_to)
        ab = b - a
        L = wp.length(ab)
        if L > 1.0e-6:
            t = wp.clamp(wp.dot(p - a, ab) / (L * L), 0.0, 1.0)
            d = wp.length(p - (a + t * ab))
            if d < best_d:
                best_d = d
                best_s = sa + t * L
                best_dir = ab / L
        if k >= n - 1 or sa > s_to:
            done = bool(True)
        k += 1
    return best_d, best_s, best_dir


@wp.func
def path_crossing(m: ModelArrays, row: int, q0: wp.vec2f, q1: wp.vec2f, k_from: int, s_to: float):
    """First crossing of segment q0-q1 with the path ahead; returns (hit, arc m, fraction along q)."""
    n = m.path_n[row]
    hit = bool(False)
    best_s = float(1.0e9)
    best_u = float(0.0)
    k = wp.max(k_from, 0)
    done = bool(False)
    sd = q1 - q0
    while not done:
        a, b, sa = _path_segment(m, row, k, n, s_to)
        r = b - a
        denom = cross2(r, sd)
        if wp.abs(denom) > 1.0e-9:
            t = cross2(q0 - a, sd) / denom
            u = cross2(q0 - a, r) / denom
            if t >= 0.0 and t <= 1.0 and u >= 0.0 and u <= 1.0:
                sc = sa + t * wp.length(r)
                if sc < best_s:
                    best_s = sc
                    best_u = u
                    hit = bool(True)
        if k >= n - 1 or sa > s_to:
            done = bool(True)
        k += 1
    return hit, best_s, best_u


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def idm_kernel(state: State, scratch: StepScratch, model: ModelArrays, params: Params):
    """IDM acceleration of every live IDM agent from the current poses (over (W, A)).

    Reads: agent_row, alive, controller, heading, idm_k, idm_s, pos, size, speed, step_count, vel
    Writes: scratch.idm_accel
    """
    w, a = wp.tid()
    if state.step_count[w] >= params.episode_steps or not state.alive[w, a] or state.controller[w, a] != IDM:
        return
    row = state.agent_row[w, a]
    s_i = state.idm_s[w, a]
    k_i = state.idm_k[w, a]
    v = wp.max(state.speed[w, a], 0.0)
    v0 = model.idm_v0[row]  # the largest logged speed; 0 for agents parked in their log
    if v0 > 0.0 and params.idm_v0 > 0.0:
        v0 = params.idm_v0
    pi = state.pos[w, a]
    hi = state.heading[w, a]
    fwd = wp.vec2f(wp.cos(hi), wp.sin(hi))
    li = state.size[w, a][0]
    wi = state.size[w, a][1]
    look = params.idm_lookahead
    s_to = s_i + look
    gap = float(1.0e9)
    v_lead = float(0.0)
    has_lead = bool(False)
    num = state.alive.shape[1]
    for j in range(num):
        if j == a or not state.alive[w, j]:
            continue
        pj = state.pos[w, j]
        rel = pj - pi
        dist = wp.length(rel)
        lj = state.size[w, j][0]
        wj = state.size[w, j][1]
        vj = state.vel[w, j]
        if dist > look + 0.5 * (li + lj) + CROSSING_HORIZON * wp.length(vj):
            continue
        if wp.dot(rel, fwd) < -0.5 * (li + lj):
            continue  # behind
        d, sp, pdir = path_project(model, row, pj, k_i, s_to)
        if d <= 0.5 * (wi + wj) + 0.3:
            g = sp - s_i - 0.5 * (li + lj)
            if g < gap and sp >= s_i:
                gap = g
                v_lead = wp.max(wp.dot(vj, pdir), 0.0)
                has_lead = bool(True)
        elif wp.length(vj) > 0.5:
            hit, sc, u = path_crossing(model, row, pj, pj + CROSSING_HORIZON * vj, k_i, s_to)
            if hit:
                t_j = CROSSING_HORIZON * u
                t_i = (sc - s_i) / wp.max(v, 0.5)
                if t_j < t_i:
                    g = sc - s_i - 0.5 * li - 0.5 * wp.max(lj, wj)
                    if g < gap:
                        gap = g
                        v_lead = 0.0
                        has_lead = bool(True)
    acc = float(0.0)
    amax = params.idm_accel
    if v0 <= 0.0:
        if v > 0.0:
            acc = -params.idm_brake
    else:
        ratio = v / v0
        acc = amax * (1.0 - ratio * ratio * ratio * ratio)
        if has_lead:
            dv = v - v_lead
            s_star = params.idm_min_gap + wp.max(
                0.0, v * params.idm_headway + v * dv / (2.0 * wp.sqrt(amax * params.idm_brake)))
            q = s_star / wp.max(gap, 0.1)
            acc = acc - amax * q * q
        acc = wp.clamp(acc, -8.0, amax)
    scratch.idm_accel[w, a] = acc


@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def idm_attach_kernel(state: State, model: ModelArrays, worlds: wp.array(dtype=wp.int32),
                      attach: wp.array2d(dtype=wp.bool)):
    """Put agents newly switched to IDM on their path at the nearest point (over (n, A)).

    Reads: agent_row, pos
    Writes: idm_k, idm_s
    """
    i, a = wp.tid()
    w = worlds[i]
    if not attach[i, a] or state.agent_row[w, a] < 0:
        return
    row = state.agent_row[w, a]
    n = model.path_n[row]
    end = model.path_s[row, wp.max(n - 1, 0)]
    d, s, pdir = path_project(model, row, state.pos[w, a], 0, end + 1000.0)
    pos, h, k = path_pose(model, row, s, 0)
    state.idm_s[w, a] = s
    state.idm_k[w, a] = k


@launcher(idm_kernel)
def launch_idm(state: State, scratch: StepScratch, model: ModelArrays, params: Params, *, dim: Any,
               device: Any = None, record: bool = False, kernel: wp.Kernel = idm_kernel) -> Any:
    """Launch the IDM kernel (``kernel``: :func:`idm_kernel` or a variant with its parameters)
    over ``dim``.

    Writes: scratch.idm_accel
    """
    return launch(kernel, launch_idm.kernels, dim, [state, scratch, model, params], device=device, record=record)


@launcher(idm_attach_kernel)
def launch_idm_attach(state: State, model: ModelArrays, worlds: wp.array, attach: wp.array, *, dim: Any,
                      device: Any = None, record: bool = False) -> Any:
    """Launch :func:`idm_attach_kernel` over ``dim`` = (len(worlds), A); ``worlds`` (n,) and
    ``attach`` (n, A) bool are read only.

    Writes: idm_k, idm_s
    """
    return launch(idm_attach_kernel, launch_idm_attach.kernels, dim, [state, model, worlds, attach],
                  device=device, record=record)


__all__ = ["path_pose", "path_project", "path_crossing", "idm_kernel", "idm_attach_kernel", "launch_idm",
           "launch_idm_attach"]
