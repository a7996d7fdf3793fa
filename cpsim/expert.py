"""Log-tracking expert in the policy's action space (a closed-loop teacher for imitation).

Log replay teleports agents along their logs; a policy has to steer with discrete jerks
(or accelerations and steering angles). :class:`TrackingExpert` closes that gap: every
step it picks, for every agent, the discrete action of the simulator's dynamics that
follows the agent's logged path (pure pursuit on the path, so the agent stays on the
road and reaches its goal) at the logged schedule (the speed the log has at this step,
plus a correction towards the logged arc position, so yields and stops in the log are
kept). The labels are exact actions of the simulator, so they can be imitated by a
policy (``cpalgo.pretrain``) from the states the policy itself visits (DAgger).

Everything is batched over worlds x agents in torch; there is no Python loop over agents.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
import warp as wp

from cpsim.config import CLASSIC_ACCEL, CLASSIC_STEER, JERK_LAT, JERK_LONG
from cpsim.kernels.dynamics import JERK_A_LAT_RANGE, JERK_A_LONG_RANGE


@dataclasses.dataclass(frozen=True)
class TrackingGains:
    """Gains of the tracking expert.

    Attributes:
        lookahead_min: shortest pure-pursuit lookahead, m.
        lookahead_time: lookahead added per m/s of speed, s.
        lookahead_max: longest lookahead, m.
        speed_gain: acceleration per m/s of speed error, 1/s.
        position_gain: acceleration per m the agent lags behind the logged arc position, 1/s^2.
        lag_cap: largest arc-position error acted on, m (so a far-behind agent does not race).
        stop_speed: logged speed below which the log is treated as stopped, m/s.
    """

    lookahead_min: float = 4.0
    lookahead_time: float = 0.8
    lookahead_max: float = 20.0
    speed_gain: float = 1.5
    position_gain: float = 0.3
    lag_cap: float = 5.0
    stop_speed: float = 0.3

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"TrackingGains.{f.name}: must be finite and >= 0, got {value!r}")
        if self.lookahead_min <= 0 or self.lookahead_max < self.lookahead_min:
            raise ValueError("TrackingGains.lookahead_min/lookahead_max: need 0 < min <= max")


class TrackingExpert:
    """Discrete actions that track every agent's log in a :class:`cpsim.Simulator`.

    Args:
        sim: the simulator whose agents are tracked (any dynamics).
        gains: controller gains.

    ``actions()`` returns an int32 tensor (W, A) of action indices for the current state;
    agents without a log (empty slots) get the "keep" action. Call it after every
    ``sim.step`` / ``sim.reset`` (it reads the live state views).
    """

    def __init__(self, sim, gains: TrackingGains | None = None) -> None:
        self.sim = sim
        self.gains = gains or TrackingGains()
        m = sim.model.arrays
        self._path_xy = torch.as_tensor(m.path_xy.numpy().view(np.float32).reshape(*m.path_s.shape, 2))
        self._path_s = torch.as_tensor(m.path_s.numpy())
        self._path_h = torch.as_tensor(m.path_h.numpy())
        self._path_n = torch.as_tensor(m.path_n.numpy()).long()
        self._log_valid = torch.as_tensor(m.log_valid.numpy())
        log_vel = torch.as_tensor(m.log_vel.numpy().view(np.float32).reshape(*m.path_s.shape, 2))
        log_xy = torch.as_tensor(m.log_xy.numpy().view(np.float32).reshape(*m.path_s.shape, 2))
        self._log_speed = torch.linalg.norm(log_vel, dim=-1)
        self._log_s = self._log_arc(log_xy)
        self._agent_row = wp.to_torch(sim.state.agent_row)  # live view: follows every reset
        self.dynamics = sim.config.dynamics
        T = self._path_s.shape[1]
        self._k = torch.arange(T)

    # ------------------------------------------------------------------ helpers
    def _log_arc(self, log_xy: torch.Tensor) -> torch.Tensor:
        """Arc length along the path at each logged step (L, T), m; invalid steps carry the
        previous value forward (so a missing step means "stay where the log was")."""
        valid = self._log_valid
        step = torch.linalg.norm(torch.diff(log_xy, dim=1), dim=-1)
        step = torch.where(valid[:, 1:] & valid[:, :-1], step, torch.zeros_like(step))
        return torch.cat([torch.zeros_like(step[:, :1]), torch.cumsum(step, dim=1)], dim=1)

    def _logged(self, values: torch.Tensor, rows: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """values[row, t], or at the last valid logged step <= t when t is not valid."""
        valid = self._log_valid[rows] & (self._k[None, :] <= t[:, None])
        k_last = (valid.long() * self._k[None, :]).amax(1)
        return values[rows, k_last]

    def _path_point(self, rows: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """Position at arc length s along each row's path (N,) -> (N, 2); past the end the
        path is extended along its last heading."""
        ps, pxy, n = self._path_s[rows], self._path_xy[rows], self._path_n[rows]
        last = (n - 1).clamp(min=0)
        inside = self._k[None, :] < n[:, None]
        k = ((ps <= s[:, None]) & inside).sum(1) - 1
        k = torch.minimum(k.clamp(min=0), (n - 2).clamp(min=0))
        idx = torch.arange(rows.numel())
        s0, s1 = ps[idx, k], ps[idx, (k + 1).clamp(max=ps.shape[1] - 1)]
        p0, p1 = pxy[idx, k], pxy[idx, (k + 1).clamp(max=ps.shape[1] - 1)]
        f = ((s - s0) / (s1 - s0).clamp(min=1e-6)).clamp(0.0, 1.0)
        point = p0 + f[:, None] * (p1 - p0)
        end_s = ps[idx, last]
        h_end = self._path_h[rows, last]
        beyond = (s - end_s).clamp(min=0.0)
        end_point = pxy[idx, last] + beyond[:, None] * torch.stack([torch.cos(h_end), torch.sin(h_end)], -1)
        return torch.where((s >= end_s)[:, None] | (n <= 1)[:, None], end_point, point)

    # ------------------------------------------------------------------ the controller
    def targets(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Desired (longitudinal acceleration, lateral acceleration) per slot, (W, A) m/s^2."""
        sim, g = self.sim, self.gains
        W, A = sim.num_worlds, sim.max_agents
        rows = self._agent_row.reshape(-1).long()
        have = rows >= 0
        rows = rows.clamp(min=0)
        pos = sim.xy.reshape(-1, 2)
        heading = sim.heading.reshape(-1)
        v = sim.speed.reshape(-1)
        t = sim.step_count.long().repeat_interleave(A)

        # project onto the logged path (nearest path vertex, then onto its segments)
        pxy, ps, n = self._path_xy[rows], self._path_s[rows], self._path_n[rows]
        inside = self._k[None, :] < n[:, None]
        d2 = ((pxy - pos[:, None, :]) ** 2).sum(-1).masked_fill(~inside, float("inf"))
        k = d2.argmin(1)
        idx = torch.arange(rows.numel())
        s_proj = ps[idx, k]
        k1 = torch.minimum(k + 1, (n - 1).clamp(min=0))
        seg = pxy[idx, k1] - pxy[idx, k]
        seg_len = torch.linalg.norm(seg, dim=-1).clamp(min=1e-6)
        along = ((pos - pxy[idx, k]) * seg).sum(-1) / seg_len
        s_proj = s_proj + along.clamp(min=0.0) * (k1 > k)

        # lateral: pure pursuit towards the lookahead point -> lateral acceleration v^2 kappa
        speed = v.abs()
        la = (g.lookahead_min + g.lookahead_time * speed).clamp(max=g.lookahead_max)
        target = self._path_point(rows, s_proj + la)
        rel = target - pos
        c, s = torch.cos(heading), torch.sin(heading)
        x_e = c * rel[:, 0] + s * rel[:, 1]
        y_e = -s * rel[:, 0] + c * rel[:, 1]
        dist = torch.sqrt(x_e ** 2 + y_e ** 2).clamp(min=1e-3)
        kappa = 2.0 * y_e / dist ** 2
        a_lat = (speed.clamp(min=1.0) ** 2 * kappa).clamp(*JERK_A_LAT_RANGE)

        # longitudinal: the logged speed of the next step, corrected towards the logged arc
        T = self._log_speed.shape[1]
        t_next = (t + 1).clamp(max=T - 1)
        t_now = t.clamp(max=T - 1)
        # no log at a step (left the log): use the last logged step before it
        v_log = self._logged(self._log_speed, rows, t_next)
        s_log = self._logged(self._log_s, rows, t_now)  # where the log is now
        lag = (s_log - s_proj).clamp(-g.lag_cap, g.lag_cap)
        v_ref = v_log + g.position_gain / max(g.speed_gain, 1e-6) * lag
        a_long = g.speed_gain * (v_ref - v)
        stopped = (v_log < g.stop_speed) & (lag < 0.5)
        a_long = torch.where(stopped, -2.0 * v.clamp(min=0.0) / 0.5, a_long)
        a_long = a_long.clamp(*JERK_A_LONG_RANGE)
        a_long = torch.where(have, a_long, torch.zeros_like(a_long))
        a_lat = torch.where(have, a_lat, torch.zeros_like(a_lat))
        return a_long.reshape(W, A), a_lat.reshape(W, A)

    def actions(self) -> torch.Tensor:
        """Action indices (W, A) int32 for the current state."""
        a_long_t, a_lat_t = self.targets()
        sim = self.sim
        dt = float(sim.config.dt)
        if self.dynamics == "jerk":
            a_long = sim.accel[..., None]
            a_lat = wp.to_torch(sim.state.lat_accel)[..., None]
            jl = torch.as_tensor(JERK_LONG)
            jt = torch.as_tensor(JERK_LAT)
            nl = _jerk_next(a_long, jl * dt, JERK_A_LONG_RANGE)
            nt = _jerk_next(a_lat, jt * dt, JERK_A_LAT_RANGE)
            il = (nl - a_long_t[..., None]).abs().argmin(-1)
            it = (nt - a_lat_t[..., None]).abs().argmin(-1)
            return (il * len(JERK_LAT) + it).to(torch.int32)
        # classic: acceleration command and steering angle (yaw rate ~ v tan(steer) / length)
        acc = torch.as_tensor(CLASSIC_ACCEL)
        steer = torch.as_tensor(CLASSIC_STEER)
        il = (acc[None, None, :] - a_long_t[..., None]).abs().argmin(-1)
        v = sim.speed.abs().clamp(min=1.0)
        steer_t = torch.atan(a_lat_t / v ** 2 * sim.size[..., 0])
        it = (steer[None, None, :] - steer_t[..., None]).abs().argmin(-1)
        return (il * steer.numel() + it).to(torch.int32)


def _jerk_next(a: torch.Tensor, delta: torch.Tensor, bounds: tuple[float, float]) -> torch.Tensor:
    """The jerk model's next acceleration for every candidate increment (sign change -> 0)."""
    new = a + delta
    return torch.where(a * new < 0.0, torch.zeros_like(new), new.clamp(*bounds))


__all__ = ["TrackingExpert", "TrackingGains"]
