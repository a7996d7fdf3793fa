"""Vehicle dynamics and the per-step motion kernel (all controllers).

Jerk model (BehaviorBench / PufferDrive "jerk", default; 12 actions,
index = long_idx * 3 + lat_idx over long jerk {-15, -4, 0, 4} x lat jerk {-4, 0, 4} m/s^3):

    a_long' = a_long + j_long dt, set to 0 if it changes sign, else clipped to [-5, 2.5]
    a_lat'  = a_lat + j_lat dt,   set to 0 if it changes sign, else clipped to [-4, 4]
    v_s = |v| signed by v . heading;  v' = v_s + (a_long + a_long') dt / 2,
          set to 0 if it changes sign, else clipped to [-2, 20]; a_long' = 0 when the
          speed was limited (the acceleration behind a refused speed change did not happen)
    kappa = a_lat' / max(v'^2, 1e-5), wheelbase = 0.6 length
    steer' = clip(steer + clip(atan(kappa wheelbase) - steer, -0.6 dt, 0.6 dt), -0.55, 0.55)
    kappa = tan(steer') / wheelbase;  a_lat' = v'^2 kappa
    d = (v' + v_s) dt / 2;  theta = d kappa;  arc (sin theta / kappa, (1 - cos theta) / kappa)
    in the heading frame (straight when |kappa| or |theta| < 1e-5); heading += theta;
    velocity = v' (cos, sin)(heading').

Two departures from PufferDrive's jerk step, both absorbing states of the original:
PufferDrive floors |kappa| at 1e-5 with the sign of a_lat' (+ for 0), so a zero lateral
command leaves the steering at +atan(1e-5 wheelbase) and a_lat at +v^2 1e-5; from there
every negative jerk changes sign and is reset to 0 again, so once an agent has steered
left and straightened out it can never steer right. And a_long was kept when the speed
limiter refused the change (stopped at 0 or the [-2, 20] bounds), so a hard stop left
a_long = -5 that only ~13 full-throttle steps could unwind (and the next steps reversed).
Here a zero command means zero curvature and a refused speed change zeroes a_long.

Classic bicycle (GPUDrive / PufferDrive 2.0; 91 actions, index = accel_idx * 13 + steer_idx
over accel {-4, -2.667, -1.333, 0, 1.333, 2.667, 4} m/s^2 x PufferDrive's rounded steering
table +-{0.167, 0.333, 0.5, 0.667, 0.833, 1} and 0 rad), identical to PufferDrive's
``move_dynamics`` step for step (``tests/cpsim/test_sim_dynamics.py`` replays its own float32
trajectories, ``../shared/data/pufferdrive/classic_kinematics.csv``):

    v = |velocity|;  v' = clip(v + a dt, -100, 100)   (v' signed: it may become negative)
    beta = tanh(0.5 tan(delta))
    yaw_rate = v' cos(beta) tan(delta) / (box_scale x length)   (the updated, signed speed)
    velocity = v' (cos, sin)(heading + beta);  position += velocity dt;
    heading = wrap(heading + yaw_rate dt)

PufferDrive multiplies the length of the agents it controls by 0.7 at load, so its yaw rate
divides by 0.7 x the logged length on WOMD; here the divisor follows ``SimConfig.box_scale``
(the same shrink used for collision and off-road geometry), so ``box_scale=0.7`` matches
PufferDrive and the default 1.0 divides by the logged length. As in PufferDrive, the next
step starts from |velocity| again, so a car pushed below zero speed oscillates around
|v| = a dt rather than reversing steadily.

Reported for metrics: a_long = the new longitudinal acceleration (jerk: state; classic: the
command; replay / IDM: finite difference of the signed speed), a_lat (jerk: state; others:
speed x yaw rate), jerk = (a_long' - a_long) / dt, lateral jerk = (a_lat' - a_lat) / dt.
Before moving, the kernel keeps the pose and velocity of the step's start (``prev_pos``,
``prev_heading``, ``prev_vel``) and writes the position into the ring ``pos_hist`` (slot
step_count % 4): the at-fault rules classify a contact from the state one step before it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import warp as wp

from cpsim.config import CLASSIC_ACCEL, CLASSIC_STEER, JERK_LAT, JERK_LONG
from cpsim.kernels.common import IDM, KERNEL_MODULE, LAST_LOG_STEP, POLICY, REPLAY, STATIC, Params, launch, launcher
from cpsim.kernels.controllers import path_pose
from cpsim.kernels.geometry import wrap_angle
from cpsim.model_arrays import ModelArrays
from cpsim.state import State, StepScratch

WHEELBASE_FRACTION = 0.6
JERK_A_LONG_RANGE = (-5.0, 2.5)
JERK_A_LAT_RANGE = (-4.0, 4.0)
JERK_SPEED_RANGE = (-2.0, 20.0)
STEER_RATE = 0.6
STEER_LIMIT = 0.55
CLASSIC_SPEED_LIMIT = 100.0
WHEELBASE = wp.constant(WHEELBASE_FRACTION)

_JERK_LONG = wp.constant(wp.types.vector(4, wp.float32)(*JERK_LONG.tolist()))
_JERK_LAT = wp.constant(wp.types.vector(3, wp.float32)(*JERK_LAT.tolist()))
_CLASSIC_ACCEL = wp.constant(wp.types.vector(7, wp.float32)(*CLASSIC_ACCEL.tolist()))
_CLASSIC_STEER = wp.constant(wp.types.vector(13, wp.float32)(*CLASSIC_STEER.tolist()))


# ============================================================================ Warp functions
@wp.func
def jerk_step(pos: wp.vec2f, heading: float, vel: wp.vec2f, a_long: float, a_lat: float,
              steer: float, length: float, j_long: float, j_lat: float, dt: float):
    """One jerk-model step. Returns (pos, heading, vel, a_long, a_lat, steer, signed speed)."""
    hx = wp.cos(heading)
    hy = wp.sin(heading)
    wheelbase = 0.6 * length
    a_long_new = a_long + j_long * dt
    a_lat_new = a_lat + j_lat * dt
    if a_long * a_long_new < 0.0:
        a_long_new = 0.0
    else:
        a_long_new = wp.clamp(a_long_new, -5.0, 2.5)
    if a_lat * a_lat_new < 0.0:
        a_lat_new = 0.0
    else:
        a_lat_new = wp.clamp(a_lat_new, -4.0, 4.0)
    speed = wp.length(vel)
    signed_v = speed
    if vel[0] * hx + vel[1] * hy < 0.0:
        signed_v = -speed
    v_target = signed_v + 0.5 * (a_long_new + a_long) * dt
    v_new = v_target
    if signed_v * v_target < 0.0:
        v_new = 0.0
    else:
        v_new = wp.clamp(v_target, -2.0, 20.0)
    if v_new != v_target:
        a_long_new = 0.0
    curv = a_lat_new / wp.max(v_new * v_new, 1.0e-5)
    target = wp.atan(curv * wheelbase)
    steer_new = wp.clamp(steer + wp.clamp(target - steer, -0.6 * dt, 0.6 * dt), -0.55, 0.55)
    curv = wp.tan(steer_new) / wheelbase
    a_lat_new = v_new * v_new * curv
    d = 0.5 * (v_new + signed_v) * dt
    theta = d * curv
    dx = d
    dy = float(0.0)
    if not (wp.abs(curv) < 1.0e-5 or wp.abs(theta) < 1.0e-5):
        dx = wp.sin(theta) / curv
        dy = (1.0 - wp.cos(theta)) / curv
    new_pos = pos + wp.vec2f(dx * hx - dy * hy, dx * hy + dy * hx)
    new_heading = wrap_angle(heading + theta)
    new_vel = wp.vec2f(v_new * wp.cos(new_heading), v_new * wp.sin(new_heading))
    return new_pos, new_heading, new_vel, a_long_new, a_lat_new, steer_new, v_new


@wp.func
def classic_step(pos: wp.vec2f, heading: float, vel: wp.vec2f, length: float, accel: float,
                 steering: float, dt: float):
    """One classic bicycle step (``length``: the length the yaw rate divides by, i.e.
    box_scale x the logged length). Returns (pos, heading, vel, signed speed, yaw rate)."""
    speed = wp.length(vel)
    speed_new = wp.clamp(speed + accel * dt, -100.0, 100.0)
    beta = wp.tanh(0.5 * wp.tan(steering))
    yaw_rate = speed_new * wp.cos(beta) * wp.tan(steering) / length
    new_vel = wp.vec2f(speed_new * wp.cos(heading + beta), speed_new * wp.sin(heading + beta))
    new_pos = pos + new_vel * dt
    new_heading = wrap_angle(heading + yaw_rate * dt)
    return new_pos, new_heading, new_vel, speed_new, yaw_rate


@wp.func
def signed_speed(vel: wp.vec2f, heading: float) -> float:
    s = wp.length(vel)
    if vel[0] * wp.cos(heading) + vel[1] * wp.sin(heading) < 0.0:
        s = -s
    return s


# ============================================================================ kernel
@wp.kernel(module=KERNEL_MODULE, enable_backward=False)
def dynamics_kernel(state: State, scratch: StepScratch, model: ModelArrays, params: Params, actions: wp.array2d(dtype=wp.int32)):
    """Move every live agent one step with its controller (over (W, A)).

    Also clears last step's done flags, stores the previous pose (swept off-road test) and
    sets ``scratch.present`` for every slot. Replayed agents whose log becomes invalid vanish here (alive False,
    done and truncated). Worlds whose episode is over are left unchanged.

    Reads: accel, agent_row, alive, controller, heading, idm_k, idm_s, lat_accel, pos, size, speed, steer,
        step_count, vel, scratch.idm_accel
    Writes: accel, alive, done, finished, heading, idm_k, idm_s, jerk, lat_accel, lat_jerk, pos, pos_hist,
        prev_heading, prev_pos, prev_vel, speed, steer, terminated, truncated, vel, scratch.present
    """
    w, a = wp.tid()
    state.done[w, a] = False
    state.terminated[w, a] = False
    state.truncated[w, a] = False
    if state.step_count[w] >= params.episode_steps or not state.alive[w, a]:
        scratch.present[w, a] = False
        return
    dt = params.dt
    ctrl = state.controller[w, a]
    pos = state.pos[w, a]
    heading = state.heading[w, a]
    vel = state.vel[w, a]
    old_speed = state.speed[w, a]
    old_accel = state.accel[w, a]
    state.prev_pos[w, a] = pos
    state.prev_heading[w, a] = heading
    state.prev_vel[w, a] = vel
    state.pos_hist[w, a, state.step_count[w] % state.pos_hist.shape[2]] = pos
    length = state.size[w, a][0]
    old_lat = state.lat_accel[w, a]
    new_pos = pos
    new_heading = heading
    new_vel = vel
    new_speed = old_speed
    new_accel = old_accel
    new_lat = old_lat
    new_steer = state.steer[w, a]
    if ctrl == POLICY:
        act = actions[w, a]
        if params.dynamics == 0:
            jl = _JERK_LONG[act // 3]
            jt = _JERK_LAT[act % 3]
            new_pos, new_heading, new_vel, new_accel, new_lat, new_steer, new_speed = jerk_step(
                pos, heading, vel, old_accel, new_lat, new_steer, length, jl, jt, dt)
        else:
            acc = _CLASSIC_ACCEL[act // 13]
            st = _CLASSIC_STEER[act % 13]
            yaw = float(0.0)
            new_pos, new_heading, new_vel, new_speed, yaw = classic_step(
                pos, heading, vel, length * params.box_scale, acc, st, dt)
            new_accel = acc
            new_lat = new_speed * yaw
            new_steer = st
    elif ctrl == REPLAY:
        row = state.agent_row[w, a]
        t = wp.min(state.step_count[w] + 1, LAST_LOG_STEP)
        if not model.log_valid[row, t]:
            # the log ends: the agent leaves the world
            state.alive[w, a] = False
            scratch.present[w, a] = False
            state.finished[w, a] = True
            state.done[w, a] = True
            state.truncated[w, a] = True
            return
        new_pos = model.log_xy[row, t]
        new_heading = model.log_heading[row, t]
        new_vel = model.log_vel[row, t]
        new_speed = signed_speed(new_vel, new_heading)
    elif ctrl == IDM:
        row = state.agent_row[w, a]
        v = wp.max(old_speed, 0.0)
        v_new = wp.max(v + scratch.idm_accel[w, a] * dt, 0.0)
        s = state.idm_s[w, a] + 0.5 * (v + v_new) * dt
        k = state.idm_k[w, a]
        new_pos, new_heading, k = path_pose(model, row, s, k)
        state.idm_s[w, a] = s
        state.idm_k[w, a] = k
        new_speed = v_new
        new_vel = wp.vec2f(v_new * wp.cos(new_heading), v_new * wp.sin(new_heading))
    elif ctrl == STATIC:
        new_vel = wp.vec2f(0.0, 0.0)
        new_speed = 0.0
    if ctrl != POLICY:
        # derived quantities for metrics: finite differences of the driven motion
        new_accel = (new_speed - old_speed) / dt
        dh = wrap_angle(new_heading - heading)
        new_lat = new_speed * dh / dt
        ds = wp.length(new_pos - pos)
        if ds > 1.0e-3:
            new_steer = wp.atan(dh / ds * WHEELBASE * length)
        if ctrl == STATIC:
            new_accel = 0.0
            new_lat = 0.0
    state.pos[w, a] = new_pos
    state.heading[w, a] = new_heading
    state.vel[w, a] = new_vel
    state.speed[w, a] = new_speed
    state.jerk[w, a] = (new_accel - old_accel) / dt
    state.lat_jerk[w, a] = (new_lat - old_lat) / dt
    state.accel[w, a] = new_accel
    state.lat_accel[w, a] = new_lat
    state.steer[w, a] = new_steer
    scratch.present[w, a] = True


@launcher(dynamics_kernel)
def launch_dynamics(state: State, scratch: StepScratch, model: ModelArrays, params: Params, actions: wp.array, *,
                    dim: Any, device: Any = None, record: bool = False, kernel: wp.Kernel = dynamics_kernel) -> Any:
    """Launch the motion kernel (``kernel``: :func:`dynamics_kernel` or a variant with its
    parameters) over ``dim``; ``actions`` (W, A) int32 is read only.

    Writes: accel, alive, done, finished, heading, idm_k, idm_s, jerk, lat_accel, lat_jerk, pos, pos_hist,
        prev_heading, prev_pos, prev_vel, speed, steer, terminated, truncated, vel, scratch.present
    """
    return launch(kernel, launch_dynamics.kernels, dim, [state, scratch, model, params, actions],
                  device=device, record=record)



# ============================================================================ NumPy references
def jerk_step_np(x, y, heading, vx, vy, a_long, a_lat, steer, length, j_long, j_lat, dt=0.1):
    """Reference jerk step in float64; returns a dict of the new state."""
    hx, hy = math.cos(heading), math.sin(heading)
    wb = WHEELBASE_FRACTION * length
    aln = a_long + j_long * dt
    atn = a_lat + j_lat * dt
    aln = 0.0 if a_long * aln < 0 else float(np.clip(aln, *JERK_A_LONG_RANGE))
    atn = 0.0 if a_lat * atn < 0 else float(np.clip(atn, *JERK_A_LAT_RANGE))
    speed = math.hypot(vx, vy)
    sv = -speed if vx * hx + vy * hy < 0 else speed
    v_target = sv + 0.5 * (aln + a_long) * dt
    vn = 0.0 if sv * v_target < 0 else float(np.clip(v_target, *JERK_SPEED_RANGE))
    if vn != v_target:
        aln = 0.0
    curv = atn / max(vn * vn, 1e-5)
    target = math.atan(curv * wb)
    steer_n = float(np.clip(steer + np.clip(target - steer, -STEER_RATE * dt, STEER_RATE * dt),
                            -STEER_LIMIT, STEER_LIMIT))
    curv = math.tan(steer_n) / wb
    atn = vn * vn * curv
    d = 0.5 * (vn + sv) * dt
    theta = d * curv
    if abs(curv) < 1e-5 or abs(theta) < 1e-5:
        dx, dy = d, 0.0
    else:
        dx, dy = math.sin(theta) / curv, (1 - math.cos(theta)) / curv
    hn = float(wrap(heading + theta))
    return {"x": x + dx * hx - dy * hy, "y": y + dx * hy + dy * hx, "heading": hn,
            "vx": vn * math.cos(hn), "vy": vn * math.sin(hn), "a_long": aln, "a_lat": atn,
            "steer": steer_n, "speed": vn}


def classic_step_np(x, y, heading, vx, vy, length, accel, steering, dt=0.1):
    """Reference classic (PufferDrive) step in float64; returns a dict of the new state.

    ``length`` is the length the yaw rate divides by (box_scale x the logged length)."""
    speed = math.hypot(vx, vy)
    sn = float(np.clip(speed + accel * dt, -CLASSIC_SPEED_LIMIT, CLASSIC_SPEED_LIMIT))
    beta = math.tanh(0.5 * math.tan(steering))
    yaw = sn * math.cos(beta) * math.tan(steering) / length
    vxn, vyn = sn * math.cos(heading + beta), sn * math.sin(heading + beta)
    return {"x": x + vxn * dt, "y": y + vyn * dt, "heading": float(wrap(heading + yaw * dt)),
            "vx": vxn, "vy": vyn, "speed": sn, "yaw_rate": yaw}


def wrap(a: float) -> float:
    return a - 2.0 * math.pi * math.floor((a + math.pi) / (2.0 * math.pi))


__all__ = ["jerk_step", "classic_step", "dynamics_kernel", "launch_dynamics", "jerk_step_np", "classic_step_np",
           "WHEELBASE_FRACTION"]
