"""Behaviour-cloning log-imitation traffic model (stands in for SMART in the evaluation).

Shipped model (``cpalgo/shipped/bc_traffic.pt`` = ``zoo/bc_traffic.pt``): DAgger against
the log-tracking expert (:class:`cpsim.expert.TrackingExpert`, which follows each agent's
logged path at the logged schedule with the simulator's own discrete actions). Round 0
drives every task vehicle with the expert (plus 10 % random actions) and fits the model;
every later round drives them with the model itself, as ``bc`` traffic does in the
evaluation (in half the worlds slot 0 replays its log, as the expert-replay ego), labels
every visited state with the expert's action from there, adds the samples to all earlier
rounds' and continues training (:func:`dagger`, :func:`traffic_rollouts`). Pools:
procedural training logs (200 drawn plus the 150 most interactive of 600 more, since the
evaluation's Interactive split is where learnt traffic crashes most) and the WOMD
training scenes, each simulated with as many slots as it has agents at t0 (at most 128),
as the evaluator does.

The model is an MLP over the observation with the condition slice zeroed (traffic does
not read reward conditions). With ``head="targets"`` (shipped) it regresses the expert's
longitudinal and lateral target accelerations and turns them into action logits with the
expert's own rule (:func:`targets_to_logits`): the jerk action set alternates from step to
step around a target, which a classifier over actions learns poorly (45 % accuracy, and
half of its agents crash or leave the road in closed loop; the targets have R^2 0.75 /
0.92 from the observation). ``head="actions"`` classifies the label directly. The model is
an SB3-compatible co-player, ``predict(obs, state, episode_start, deterministic) ->
(actions, None)``; ``forward`` gives action logits for either head; it is saved as a small
``.pt`` file (float16 weights).

The older labelling (``--mode``, without ``--dagger``) is kept: every agent on log replay
(and on noisy tracking with those labels), labelled with the action that, held for
``--lookahead`` steps, best reproduces the logged state, found by restoring the chunk's
worlds into a probe simulator with one copy per action (:func:`labelled_steps`).

Command of the shipped model (its ``meta`` and ``cpalgo/shipped/bc_traffic.json`` record
the rounds, timings and the before/after measurement with the expert-replay ego)::

    python -m cpalgo.traffic --out cpalgo/shipped/bc_traffic.pt --scenarios 200 --interactive 150 \
        --extra-pool ../shared/data/womd/train --worlds 64 --max-agents 128 \
        --dagger 1,0,0,0,0,0,0 --head targets --hidden 256 256 --first-epochs 10 \
        --round-epochs 4 --batch-size 256 --lr 1e-3 --noise 0.1 --keep 0.5 \
        --report cpalgo/shipped/bc_traffic.json --eval-n 50 \
        --eval-womd ../shared/data/womd/valid --eval-womd-n 50
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch as th
from torch import nn

from cpsim.arrays import to_numpy as _np
from cpsim.atomic import atomic_path
from cpsim.config import known_fields

FORMAT_VERSION = 1
# cpsim.config enum values (contract in docs/ARCHITECTURE.md)
_POLICY, _REPLAY = 0, 1
#: Heading error (rad) and speed error (m/s) are converted to metres with these scales
#: before they are added to the position error when choosing the label.
HEADING_SCALE_M = 4.0
SPEED_SCALE_S = 0.1
#: Weight of the lateral position error relative to the longitudinal one.
LATERAL_WEIGHT = 2.0


# ============================================================================ model
HEADS = ("actions", "targets")
#: Scales (m/s^2) of the ``targets`` head's outputs: longitudinal, lateral acceleration.
TARGET_SCALE = (5.0, 4.0)


def targets_to_logits(targets: th.Tensor, obs: th.Tensor, dynamics: str = "jerk", dt: float = 0.1) -> th.Tensor:
    """Logits (n, num_actions) of the actions that move each agent towards target
    accelerations (n, 2) m/s^2; the argmax is :func:`targets_to_actions`.

    The rule of :meth:`cpsim.expert.TrackingExpert.actions`, read from the observation
    (own acceleration, lateral acceleration, speed and length, :mod:`cpsim.observation`):
    jerk model: per axis, the jerk whose next acceleration is nearest the target; classic:
    the nearest acceleration command and the steering angle of the target yaw rate. The
    logit of an action is ``-0.5 sum_axis (miss / spacing)^2`` (miss: its distance to the
    target on that axis, spacing: the action grid's step on it), so the distribution is
    the rule's choice, softened over the neighbouring actions.
    """
    from cpsim.config import CLASSIC_ACCEL, CLASSIC_STEER, JERK_LAT, JERK_LONG
    from cpsim.expert import _jerk_next
    from cpsim.kernels.dynamics import JERK_A_LAT_RANGE, JERK_A_LONG_RANGE

    t_long, t_lat = targets[:, 0:1], targets[:, 1:2]
    if dynamics == "jerk":
        jl = th.as_tensor(JERK_LONG, dtype=th.float32) * dt
        jt = th.as_tensor(JERK_LAT, dtype=th.float32) * dt
        nl = _jerk_next(obs[:, 1:2] * 5.0, jl, JERK_A_LONG_RANGE)
        nt = _jerk_next(obs[:, 2:3] * 4.0, jt, JERK_A_LAT_RANGE)
        miss_l = (nl - t_long) / float(np.diff(np.sort(JERK_LONG)).min() * dt)
        miss_t = (nt - t_lat) / float(np.diff(np.sort(JERK_LAT)).min() * dt)
    else:
        acc = th.as_tensor(CLASSIC_ACCEL, dtype=th.float32)
        steer = th.as_tensor(CLASSIC_STEER, dtype=th.float32)
        v = (obs[:, 0:1] * 20.0).abs().clamp(min=1.0)
        steer_t = th.atan(t_lat / v ** 2 * obs[:, 4:5] * 10.0)
        miss_l = (acc[None, :] - t_long) / float(np.diff(CLASSIC_ACCEL).min())
        miss_t = (steer[None, :] - steer_t) / float(np.diff(CLASSIC_STEER).min())
    # action index = i_long * (lateral choices) + i_lat
    return -0.5 * (miss_l[:, :, None] ** 2 + miss_t[:, None, :] ** 2).reshape(targets.shape[0], -1)


def targets_to_actions(targets: th.Tensor, obs: th.Tensor, dynamics: str = "jerk", dt: float = 0.1) -> th.Tensor:
    """Discrete actions (n,) that move each agent towards target accelerations (n, 2) m/s^2
    (the tracking expert's rule; see :func:`targets_to_logits`)."""
    return targets_to_logits(targets, obs, dynamics, dt).argmax(-1)


class BCPolicy(nn.Module):
    """MLP over observations -> action logits, or -> target accelerations.

    Args:
        obs_size: D, the simulator's observation size.
        num_actions: size of the action set (12 for the jerk model).
        hidden: hidden layer widths.
        condition_slice: (start, stop) of the reward-condition slice in the observation;
            zeroed before the MLP so the model ignores conditions.
        obs_scale: (D,) per-feature scale the input is divided by (from the training data).
        head: ``actions`` (a classifier over the action set) or ``targets`` (regresses the
            tracking expert's longitudinal and lateral target accelerations, scaled by
            :data:`TARGET_SCALE`; :meth:`forward` turns them into action logits with
            :func:`targets_to_logits`, the expert's own rule, so the jerk set's
            step-to-step alternation need not be learnt). Either way ``forward`` gives
            action logits (SPICED's reference reads them).
        dynamics, dt: the simulator's dynamics model and step (``targets`` head).
    """

    def __init__(self, obs_size: int, num_actions: int, hidden: Sequence[int] = (128, 128),
                 condition_slice: tuple[int, int] | None = None, obs_scale: np.ndarray | None = None,
                 meta: dict[str, Any] | None = None, head: str = "actions", dynamics: str = "jerk",
                 dt: float = 0.1):
        super().__init__()
        if obs_size < 1 or num_actions < 2:
            raise ValueError(f"obs_size must be >= 1 and num_actions >= 2, got {obs_size}, {num_actions}")
        if head not in HEADS:
            raise ValueError(f"head: unknown head {head!r}; accepted: {list(HEADS)}")
        if dynamics not in ("jerk", "classic"):
            raise ValueError(f"dynamics: expected 'jerk' or 'classic', got {dynamics!r}")
        self.obs_size = int(obs_size)
        self.num_actions = int(num_actions)
        self.hidden = tuple(int(h) for h in hidden)
        self.head = head
        self.dynamics = dynamics
        self.dt = float(dt)
        self.condition_slice = None if condition_slice is None else (int(condition_slice[0]), int(condition_slice[1]))
        mask = th.ones(self.obs_size)
        if self.condition_slice is not None:
            mask[self.condition_slice[0]:self.condition_slice[1]] = 0.0
        scale = th.ones(self.obs_size) if obs_scale is None else th.as_tensor(np.asarray(obs_scale), dtype=th.float32)
        self.register_buffer("input_gain", mask / scale.clamp_min(1e-3))
        layers: list[nn.Module] = []
        width = self.obs_size
        for h in self.hidden:
            layers += [nn.Linear(width, h), nn.Tanh()]
            width = h
        layers.append(nn.Linear(width, self.num_actions if head == "actions" else 2))
        self.net = nn.Sequential(*layers)
        self.meta = dict(meta or {})

    def raw(self, obs: th.Tensor) -> th.Tensor:
        """(n, D) observations -> the network's output: (n, num_actions) logits
        (``actions`` head) or (n, 2) target accelerations / :data:`TARGET_SCALE`."""
        return self.net(obs * self.input_gain)

    def forward(self, obs: th.Tensor) -> th.Tensor:
        """(n, D) observations -> (n, num_actions) action logits, whatever the head
        (``targets``: :func:`targets_to_logits` of the predicted targets)."""
        out = self.raw(obs)
        if self.head == "targets":
            return targets_to_logits(out * th.as_tensor(TARGET_SCALE), obs, self.dynamics, self.dt)
        return out

    def for_dynamics(self, dynamics: str, dt: float | None = None) -> "BCPolicy":
        """A copy of this ``targets``-head model that acts in ``dynamics`` (step ``dt``,
        default this model's): its target accelerations become that dynamics' actions
        (:func:`targets_to_logits`). ``ValueError`` for an ``actions`` head, whose classes
        are one dynamics' action set."""
        import copy

        from cpsim.config import num_actions

        if self.head != "targets":
            raise ValueError(f"dynamics: an 'actions'-head BC model acts in {self.dynamics} dynamics only "
                             f"({self.num_actions} actions); only the 'targets' head converts to {dynamics!r}")
        n = num_actions(dynamics)  # ValueError for an unknown model
        other = copy.deepcopy(self)
        other.dynamics = dynamics
        other.num_actions = n
        other.dt = float(self.dt if dt is None else dt)
        return other

    def act(self, obs: th.Tensor, deterministic: bool = True) -> th.Tensor:
        """(n, D) float32 observations -> (n,) int64 actions (argmax, or a sample)."""
        logits = self.forward(obs)
        if deterministic:
            return logits.argmax(-1)
        return th.distributions.Categorical(logits=logits).sample()

    # SB3-compatible co-player interface --------------------------------------------
    @th.no_grad()
    def predict(self, observation: np.ndarray, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, None]:
        """SB3's signature. Deterministic: argmax; else a sample. Stateless (state None)."""
        obs = th.as_tensor(np.asarray(observation, np.float32)).reshape(-1, self.obs_size)
        return self.act(obs, deterministic).numpy().astype(np.int64), None

    # persistence ---------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Write the checkpoint atomically (temp file + ``os.replace``), weights in float16."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "format": "cpalgo.bc", "version": FORMAT_VERSION, "obs_size": self.obs_size,
            "num_actions": self.num_actions, "hidden": list(self.hidden),
            "condition_slice": self.condition_slice, "meta": self.meta,
            "head": self.head, "dynamics": self.dynamics, "dt": self.dt,
            "state_dict": {k: v.detach().to(th.float16) for k, v in self.state_dict().items()},
        }
        with atomic_path(path) as tmp:
            th.save(payload, tmp)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "BCPolicy":
        """Load a checkpoint written by :meth:`save`; ``ValueError`` naming the file otherwise."""
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"bc checkpoint {str(path)!r} does not exist")
        try:
            payload = th.load(path, map_location="cpu", weights_only=False)
        except Exception as exc:  # noqa: BLE001 - re-raised with the file name
            raise ValueError(f"bc checkpoint {str(path)!r}: cannot read ({type(exc).__name__}: {exc})") from None
        if not isinstance(payload, dict) or payload.get("format") != "cpalgo.bc":
            raise ValueError(f"bc checkpoint {str(path)!r}: not a cpalgo.bc checkpoint")
        if payload.get("version") != FORMAT_VERSION:
            raise ValueError(f"bc checkpoint {str(path)!r}: version {payload.get('version')} "
                             f"(this code reads {FORMAT_VERSION})")
        model = cls(payload["obs_size"], payload["num_actions"], payload["hidden"],
                    payload["condition_slice"], meta=payload.get("meta"), head=payload.get("head", "actions"),
                    dynamics=payload.get("dynamics", "jerk"), dt=payload.get("dt", 0.1))
        model.load_state_dict({k: v.float() for k, v in payload["state_dict"].items()})
        model.eval()
        return model


# ============================================================================ data
@dataclasses.dataclass
class BCData:
    """Samples for behaviour cloning: ``obs`` (n, D) float32 (or float16), ``actions`` (n,)
    int64, ``error_m`` (n,) float32 the label's reproduction error (m), ``scenario`` (n,)
    int64; ``targets`` (n, 2) float32 the tracking expert's target accelerations (m/s^2)
    where the labels come from it (DAgger), else None."""

    obs: np.ndarray
    actions: np.ndarray
    error_m: np.ndarray
    scenario: np.ndarray
    targets: np.ndarray | None = None


def _padded_logs(scenarios: Sequence[Any]) -> tuple[np.ndarray, ...]:
    """(S, N_max+1, T, ...) padded logs (last agent row: padding for slot index -1)."""
    n_max = max(s.num_agents for s in scenarios)
    T = scenarios[0].num_steps
    xy = np.zeros((len(scenarios), n_max + 1, T, 2), np.float32)
    heading = np.zeros((len(scenarios), n_max + 1, T), np.float32)
    speed = np.zeros((len(scenarios), n_max + 1, T), np.float32)
    valid = np.zeros((len(scenarios), n_max + 1, T), bool)
    ctrl = np.zeros((len(scenarios), n_max + 1), bool)
    for i, s in enumerate(scenarios):  # once per pool
        n = s.num_agents
        xy[i, :n], heading[i, :n], speed[i, :n] = s.log_xy, s.log_heading, s.log_speed
        valid[i, :n] = s.log_valid
        ctrl[i, :n] = s.controllable
    return xy, heading, speed, valid, ctrl


COLLECT_MODES = ("replay", "track", "both")


def _neutral_action(cfg: Any) -> int:
    """Index of the zero-jerk (jerk model) / zero-accel, zero-steer (classic) action."""
    from cpsim.config import CLASSIC_ACCEL, CLASSIC_STEER, JERK_LAT, JERK_LONG

    if cfg.dynamics == "jerk":
        return int(np.argmin(np.abs(JERK_LONG))) * JERK_LAT.size + int(np.argmin(np.abs(JERK_LAT)))
    return int(np.argmin(np.abs(CLASSIC_ACCEL))) * CLASSIC_STEER.size + int(np.argmin(np.abs(CLASSIC_STEER)))


@dataclasses.dataclass
class LabelledStep:
    """One decision of one chunk of worlds in :func:`labelled_steps` (arrays are (W, A)).

    ``obs`` (W, A, D) the observations before the decision; ``labels`` the best-reproducing
    actions, meaningful where ``labelled``; ``actions`` what the agents then did (label,
    random action or neutral); ``alive`` agents present; ``task_agents`` controllable
    agents of real (not padding) worlds; ``rewards`` the step's conditioned rewards;
    ``scenario`` (W,) pool indices; ``error_m`` the label's position error H steps ahead;
    ``t`` the decision index and ``last`` whether it is the chunk's last decision.
    """

    t: int
    last: bool
    obs: np.ndarray
    labels: np.ndarray
    labelled: np.ndarray
    actions: np.ndarray
    alive: np.ndarray
    task_agents: np.ndarray
    rewards: np.ndarray
    scenario: np.ndarray
    error_m: np.ndarray


def labelled_steps(scenarios: Sequence[Any], num_worlds: int = 32, max_agents: int = 32, sim_config: Any = None,
                   seed: int = 0, progress: bool = False, lookahead: int = 5, mode: str = "replay",
                   noise: float = 0.2, full_horizon: bool = False):
    """Yield a :class:`LabelledStep` per decision and chunk of ``num_worlds`` scenarios.

    ``mode`` is ``replay`` or ``track`` (see :func:`collect`). With ``full_horizon`` the
    chunk runs all ``episode_steps`` decisions (steps without a log ``lookahead`` ahead get
    no label); otherwise it stops at the last labelable step.
    """
    if mode not in ("replay", "track"):
        raise ValueError(f"mode: unknown collection mode {mode!r}; accepted: ['replay', 'track']")
    if lookahead < 1:
        raise ValueError(f"lookahead: must be >= 1, got {lookahead}")
    if not 0.0 <= noise <= 1.0:
        raise ValueError(f"noise: must lie in [0, 1], got {noise}")
    import cpsim
    from cpsim.config import SimConfig

    scenarios = list(scenarios)
    if not scenarios:
        raise ValueError("scenarios: empty; behaviour cloning needs logs")
    cfg = sim_config or SimConfig()
    K = int(cfg.num_actions)
    W = int(min(num_worlds, len(scenarios)))
    sim = cpsim.Simulator(scenarios, num_worlds=W, max_agents=max_agents, config=cfg, seed=seed)
    probe = cpsim.Simulator(sim.model, num_worlds=W * K, max_agents=max_agents, config=cfg, seed=seed)
    A = int(sim.max_agents)
    log_xy, log_h, log_v, log_valid, log_ctrl = _padded_logs(scenarios)
    H = int(lookahead)
    T_log = scenarios[0].num_steps
    labelable = int(min(cfg.episode_steps, T_log - 1 - H))
    if labelable < 1:
        raise ValueError(f"lookahead: {H} leaves no step of the logs to label")
    horizon = int(cfg.episode_steps) if full_horizon else labelable
    rng = np.random.default_rng(seed)
    neutral = _neutral_action(cfg)
    source = np.repeat(np.arange(W), K)  # probe world i copies chunk world i // K
    probe_actions = np.broadcast_to(np.tile(np.arange(K), W)[:, None], (W * K, A)).astype(np.int64)
    all_worlds = np.arange(W)
    tracked = mode == "track"
    for start in range(0, len(scenarios), W):
        idx = np.arange(start, min(start + W, len(scenarios)))
        scen_index = np.concatenate([idx, np.full(W - idx.size, idx[0])])
        sim.reset(scenario_index=scen_index)
        agent = _np(sim.agent_index).copy()
        a_safe = np.where(agent >= 0, agent, log_xy.shape[1] - 1)
        s_idx = scen_index[:, None]
        usable_world = np.zeros(W, bool)
        usable_world[: idx.size] = True
        controllable = (agent >= 0) & log_ctrl[s_idx, a_safe]
        task_agents = controllable & usable_world[:, None]
        sim.set_controllers(np.where(controllable & tracked, _POLICY, _REPLAY).astype(np.int32))
        for t in range(horizon):
            alive = _np(sim.alive).copy()
            obs = _np(sim.obs).copy()
            ok = np.zeros((W, A), bool)
            if t < labelable:
                ok = controllable & log_valid[s_idx, a_safe, t] & log_valid[s_idx, a_safe, t + H] \
                    & alive & usable_world[:, None]
            best = np.full((W, A), neutral, np.int64)
            err = np.zeros((W, A), np.float32)
            if ok.any():
                snap = sim.snapshot(all_worlds)
                probe.restore(snap, np.arange(W * K), source=source)
                # only the labelled agents take the candidate action; everyone else keeps
                # its controller (log replay stays log replay)
                ctrl = np.where(ok, _POLICY, _np(sim.controllers)).astype(np.int32)
                probe.set_controllers(np.repeat(ctrl, K, axis=0))
                # cost summed over the held steps: an action that overshoots and comes
                # back is worse than one that stays near the log all along
                cost = np.zeros((W, K, A))
                for k in range(1, H + 1):
                    probe.step(probe_actions)
                    pxy = _np(probe.xy).reshape(W, K, A, 2)
                    ph = _np(probe.heading).reshape(W, K, A)
                    pv = _np(probe.speed).reshape(W, K, A)
                    tk = t + k
                    ok_k = log_valid[s_idx, a_safe, tk][:, None]
                    txy = log_xy[s_idx, a_safe, tk][:, None]  # (W, 1, A, 2)
                    th_ = log_h[s_idx, a_safe, tk][:, None]
                    tv = log_v[s_idx, a_safe, tk][:, None]
                    diff = pxy - txy
                    # lateral error (across the logged heading) weighs more than the
                    # longitudinal one, which is mostly a matter of timing
                    lon = diff[..., 0] * np.cos(th_) + diff[..., 1] * np.sin(th_)
                    lat = -diff[..., 0] * np.sin(th_) + diff[..., 1] * np.cos(th_)
                    dh = np.abs((ph - th_ + np.pi) % (2 * np.pi) - np.pi)
                    step_cost = np.abs(lon) + LATERAL_WEIGHT * np.abs(lat) + HEADING_SCALE_M * dh \
                        + SPEED_SCALE_S * np.abs(pv - tv)
                    cost += np.where(ok_k, step_cost, 0.0)
                dpos = np.linalg.norm(diff, axis=-1)  # (W, K, A) at t + H
                best = np.where(ok, cost.argmin(1), neutral)  # (W, A)
                err = np.take_along_axis(dpos, best[:, None], 1)[:, 0].astype(np.float32)
            actions = best.copy()
            if tracked:
                explore = rng.random((W, A)) < noise
                actions = np.where(explore, rng.integers(0, K, (W, A)), actions)
            sim.step(actions)
            yield LabelledStep(t=t, last=t == horizon - 1, obs=obs, labels=best, labelled=ok, actions=actions,
                               alive=alive, task_agents=task_agents, rewards=_np(sim.reward).copy(),
                               scenario=scen_index.copy(), error_m=err)
        if progress:
            print(f"[{mode}] labelled {min(start + W, len(scenarios))}/{len(scenarios)} scenarios", file=sys.stderr)


def collect(scenarios: Sequence[Any], num_worlds: int = 32, max_agents: int = 32, sim_config: Any = None,
            seed: int = 0, progress: bool = False, lookahead: int = 5, mode: str = "replay",
            noise: float = 0.2) -> BCData:
    """Observations and best-reproducing action labels (see module docstring).

    Args:
        lookahead: the candidate action is held for this many steps and compared with the
            log that many steps ahead (one step of jerk moves a car by millimetres, too
            little to tell actions apart; 0.5 s separates them by decimetres). Samples need
            a valid log at ``t`` and ``t + lookahead``.
        mode: ``replay``: every agent follows its log (teacher forcing; observations are
            exactly the logged situations). ``track``: controllable agents drive with the
            label itself (the action that best returns to the log), replaced by a uniformly
            random action with probability ``noise``; the observations then include
            states off the log whose labels steer back to it (DART-style noise injection
            against the compounding errors of plain behaviour cloning). ``both``: the two
            passes over the same scenarios.
        noise: random-action probability of the ``track`` mode.
    """
    if mode not in COLLECT_MODES:
        raise ValueError(f"mode: unknown collection mode {mode!r}; accepted: {list(COLLECT_MODES)}")
    if mode == "both":
        parts = [collect(scenarios, num_worlds, max_agents, sim_config, seed, progress, lookahead, m, noise)
                 for m in ("replay", "track")]
        return aggregate(parts)
    obs_out, act_out, err_out, sc_out = [], [], [], []
    for step in labelled_steps(scenarios, num_worlds, max_agents, sim_config, seed, progress, lookahead, mode, noise):
        ok = step.labelled
        if ok.any():
            obs_out.append(step.obs[ok].astype(np.float32))
            act_out.append(step.labels[ok].astype(np.int64))
            err_out.append(step.error_m[ok])
            sc_out.append(np.broadcast_to(step.scenario[:, None], ok.shape)[ok].astype(np.int64))
    if not act_out:
        raise ValueError("scenarios: no controllable vehicle with valid log steps to label")
    return BCData(np.concatenate(obs_out), np.concatenate(act_out), np.concatenate(err_out),
                  np.concatenate(sc_out))


# ============================================================================ training
@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """BC training settings (frozen; :meth:`from_dict` rejects unknown keys)."""

    hidden: tuple[int, ...] = (128, 128)
    epochs: int = 15
    batch_size: int = 512
    lr: float = 2e-3
    weight_decay: float = 1e-5
    val_fraction: float = 0.15
    seed: int = 0
    head: str = "actions"

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TrainConfig":
        return cls(**known_fields(cls, d, "TrainConfig"))

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.batch_size < 1 or self.lr <= 0 or not 0 <= self.val_fraction < 1:
            raise ValueError(f"TrainConfig: invalid values {self}")
        if self.head not in HEADS:
            raise ValueError(f"TrainConfig.head: unknown head {self.head!r}; accepted: {list(HEADS)}")


@th.no_grad()
def _accuracy(model: BCPolicy, x: th.Tensor, y: th.Tensor, batch: int = 8192) -> float:
    """Share of deterministic actions equal to ``y``, in batches (the data may be large)."""
    hits = 0
    for b in range(0, x.shape[0], batch):
        hits += int((model.act(x[b:b + batch].float()) == y[b:b + batch]).sum())
    return hits / max(x.shape[0], 1)


def train(data: BCData, num_actions: int, condition_slice: tuple[int, int] | None = None,
          config: TrainConfig | None = None, log: bool = False, init: BCPolicy | None = None,
          dynamics: str = "jerk", dt: float = 0.1) -> tuple[BCPolicy, dict[str, float]]:
    """Fit a :class:`BCPolicy` by cross-entropy; validation split by scenario (no leakage).

    ``data.obs`` may be float16 (DAgger aggregates are stored so); batches are cast to
    float32. ``init``: continue training this model (its input scale and widths are kept;
    DAgger rounds warm-start from the previous round) instead of a fresh one. With
    ``config.head == "targets"`` the model regresses ``data.targets`` (Huber loss on the
    scaled accelerations); its accuracies compare the actions it takes with the labels.

    Returns the model and metrics: ``train_accuracy``, ``val_accuracy``,
    ``val_majority_accuracy`` (always predicting the most common action), sample counts.
    """
    cfg = config or TrainConfig()
    n = data.actions.shape[0]
    if n < 10:
        raise ValueError(f"data: {n} samples are too few to train on")
    rng = np.random.default_rng(cfg.seed)
    th.manual_seed(cfg.seed)
    scen = np.unique(data.scenario)
    val_scen = rng.choice(scen, size=max(1, int(round(cfg.val_fraction * scen.size))), replace=False) \
        if cfg.val_fraction > 0 and scen.size > 1 else np.zeros(0, np.int64)
    val = np.isin(data.scenario, val_scen)
    tr = ~val
    if init is not None:
        if init.obs_size != data.obs.shape[1] or init.num_actions != num_actions:
            raise ValueError(f"init: model of obs_size {init.obs_size} / {init.num_actions} actions does not "
                             f"fit data of {data.obs.shape[1]} features / {num_actions} actions")
        model = init
        if model.head != cfg.head:
            raise ValueError(f"init: a {model.head!r} model cannot continue as a {cfg.head!r} model")
    else:
        scale = np.maximum(np.abs(data.obs[tr]).max(0).astype(np.float32), 1.0)  # features ~[-1, 1]
        model = BCPolicy(data.obs.shape[1], num_actions, cfg.hidden, condition_slice, obs_scale=scale,
                         head=cfg.head, dynamics=dynamics, dt=dt)
    if cfg.head == "targets" and data.targets is None:
        raise ValueError("data: the 'targets' head needs data.targets (DAgger samples)")
    x = th.as_tensor(data.obs)
    y = th.as_tensor(data.actions)
    xtr, ytr = x[th.as_tensor(tr)], y[th.as_tensor(tr)]
    if cfg.head == "targets":
        ztr = th.as_tensor(data.targets[tr] / np.asarray(TARGET_SCALE, np.float32))
    opt = th.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = th.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=cfg.epochs)
    for epoch in range(cfg.epochs):
        model.train()
        perm = th.randperm(xtr.shape[0])
        total = 0.0
        for b in range(0, xtr.shape[0], cfg.batch_size):
            i = perm[b:b + cfg.batch_size]
            if cfg.head == "targets":
                loss = nn.functional.smooth_l1_loss(model.raw(xtr[i].float()), ztr[i], beta=0.1)
            else:
                loss = nn.functional.cross_entropy(model(xtr[i].float()), ytr[i])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * i.numel()
        sched.step()
        if log:
            print(f"epoch {epoch + 1}/{cfg.epochs}: loss {total / max(xtr.shape[0], 1):.4f}", file=sys.stderr)
    model.eval()
    acc_tr = _accuracy(model, xtr, ytr)
    if val.any():
        xv, yv = x[th.as_tensor(val)], y[th.as_tensor(val)]
        acc_v = _accuracy(model, xv, yv)
        majority = int(np.bincount(data.actions[tr], minlength=num_actions).argmax())
        maj_v = float((yv == majority).float().mean())
    else:
        acc_v = maj_v = float("nan")
    metrics = {"train_accuracy": acc_tr, "val_accuracy": acc_v, "val_majority_accuracy": maj_v,
               "train_samples": int(tr.sum()), "val_samples": int(val.sum()),
               "label_error_m_mean": float(data.error_m.mean())}
    return model, metrics


# ============================================================================ DAgger
@dataclasses.dataclass
class RolloutStats:
    """Closed-loop quality of one DAgger rollout pass (``scenarios`` worlds, one episode each).

    ``learner_agents`` / ``expert_agents``: task vehicles driven by the model / by the
    tracking expert; ``learner_harm_rate`` / ``expert_harm_rate``: the share of them that
    collided or went off-road; ``harm_per_world``: vehicles other than slot 0 (scenery
    included) that collided or went off-road, per world (the evaluation's co-player harm
    when slot 0 is the ego); ``samples``: labelled samples kept.
    """

    scenarios: int = 0
    learner_agents: int = 0
    expert_agents: int = 0
    learner_harm_rate: float = float("nan")
    expert_harm_rate: float = float("nan")
    harm_per_world: float = float("nan")
    samples: int = 0
    seconds: float = 0.0


def traffic_rollouts(scenarios: Sequence[Any], model: BCPolicy | None = None, beta: float = 1.0, *,
                     num_worlds: int = 64, max_agents: int = 64, sim_config: Any = None, seed: int = 0,
                     noise: float = 0.0, ego_replay: float = 0.5, keep: float = 1.0,
                     coplayers: str = "controllable", progress: bool = False) -> tuple[BCData, RolloutStats]:
    """One DAgger pass: drive every scenario once as traffic and label the visited states.

    ``scenarios``: the pool, or a prebuilt :class:`cpsim.model.Model` of it (building the road
    grids of WOMD scenes costs seconds per scene; :func:`dagger` builds it once).

    Every task vehicle (under the ``coplayers`` rule of :mod:`cpsim.envs.regimes`:
    ``controllable`` agents, or every ``vehicles`` present at t0) is a POLICY agent; in a share ``ego_replay`` of
    the worlds slot 0 (the scenario's ego) follows its log instead, as the expert-replay
    ego of the evaluation does. Each task vehicle is driven for the whole episode by
    :class:`cpsim.expert.TrackingExpert` with probability ``beta`` (a per-agent coin;
    expert-driven agents take a uniformly random action with probability ``noise`` per
    step) and by ``model``'s argmax otherwise (the evaluation's deterministic traffic).
    Every alive POLICY agent's observation is a sample (kept with probability ``keep``)
    and its label is the tracking expert's action in that state: the action that follows
    the agent's logged path at the logged schedule from wherever the agent now is.

    The simulator uses the evaluation's goal test (``goal_criterion="evaluation"``) unless
    ``sim_config`` says otherwise. Returns the samples (``obs`` float16) and
    :class:`RolloutStats`.
    """
    import cpsim
    from cpsim.config import SimConfig
    from cpsim.envs.regimes import controllable_table
    from cpsim.expert import TrackingExpert
    from cpsim.model import Model
    from cpsim.scenario.datatypes import AgentType

    pool = scenarios if isinstance(scenarios, Model) else None
    scenarios = list(pool.scenarios if pool is not None else scenarios)
    if not scenarios:
        raise ValueError("scenarios: empty; DAgger needs logs")
    if not 0.0 <= beta <= 1.0 or not 0.0 <= noise <= 1.0 or not 0.0 <= ego_replay <= 1.0 or not 0.0 < keep <= 1.0:
        raise ValueError(f"beta, noise, ego_replay must lie in [0, 1] and keep in (0, 1]; got "
                         f"{beta}, {noise}, {ego_replay}, {keep}")
    if model is None and beta < 1.0:
        raise ValueError("model: needed when beta < 1 (the learner drives a share 1 - beta of the agents)")
    t0 = time.perf_counter()
    cfg = pool.config if pool is not None else sim_config or SimConfig().replace(goal_criterion="evaluation")
    W = int(min(num_worlds, len(scenarios)))
    sim = cpsim.Simulator(pool if pool is not None else scenarios, num_worlds=W, max_agents=max_agents, config=cfg, seed=seed)
    A = int(sim.max_agents)
    K = int(cfg.num_actions)
    expert = TrackingExpert(sim)
    table = controllable_table(scenarios, coplayers)
    vehicle = np.zeros_like(table)
    for i, sc in enumerate(scenarios):  # once per pool
        vehicle[i, : sc.num_agents] = sc.agent_types == int(AgentType.VEHICLE)
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(scenarios))
    horizon = int(cfg.episode_steps)
    obs_out, act_out, sc_out, tg_out = [], [], [], []
    harmed_l = harmed_e = n_l = n_e = 0
    harm_world = 0
    n_worlds = 0
    for start in range(0, len(order), W):
        idx = order[start:start + W]
        real = np.arange(W) < idx.size
        scen_index = np.concatenate([idx, np.full(W - idx.size, idx[0])])
        sim.reset(scenario_index=scen_index)
        agent = _np(sim.agent_index).copy()
        task = table[scen_index[:, None], agent] & (agent >= 0) & real[:, None]
        ctrl = _np(sim.controllers).astype(np.int32).copy()
        ctrl[task] = _POLICY
        ego_rep = rng.random(W) < ego_replay
        ctrl[ego_rep, 0] = _REPLAY
        sim.set_controllers(ctrl)
        driven = task & (ctrl == _POLICY)
        by_expert = (rng.random((W, A)) < beta) & driven
        for _ in range(horizon):
            acting = _np(sim.policy_mask) & driven
            if not acting.any():
                break
            obs = _np(sim.obs)
            labels = _np(expert.actions()).astype(np.int64)
            targets = np.stack([_np(x) for x in expert.targets()], -1).astype(np.float32)
            actions = labels.copy()
            learner = acting & ~by_expert
            if learner.any():
                actions[learner] = model.predict(obs[learner], deterministic=True)[0]
            if noise > 0:
                flip = by_expert & (rng.random((W, A)) < noise)
                actions = np.where(flip, rng.integers(0, K, (W, A)), actions)
            rec = acting & (rng.random((W, A)) < keep) if keep < 1.0 else acting
            if rec.any():
                obs_out.append(obs[rec].astype(np.float16))
                act_out.append(labels[rec])
                tg_out.append(targets[rec])
                sc_out.append(np.broadcast_to(scen_index[:, None], (W, A))[rec].astype(np.int64))
            sim.step(actions)
            if bool(_np(sim.step_count).min() >= horizon):
                break
        met = sim.metrics
        harmed = (_np(met["first_collision_step"]) >= 0) | (_np(met["first_offroad_step"]) >= 0)
        veh = driven & vehicle[scen_index[:, None], agent]
        harmed_l += int((harmed & veh & ~by_expert).sum())
        harmed_e += int((harmed & veh & by_expert).sum())
        n_l += int((veh & ~by_expert).sum())
        n_e += int((veh & by_expert).sum())
        co = harmed & vehicle[scen_index[:, None], agent] & (agent >= 0)  # as the evaluation counts it
        co[:, 0] = False
        harm_world += int(co[real].sum())
        n_worlds += int(real.sum())
        if progress:
            print(f"[dagger beta={beta:g}] {start + idx.size}/{len(order)} scenarios", file=sys.stderr)
    if not act_out:
        raise ValueError("scenarios: no task vehicle to drive")
    data = BCData(np.concatenate(obs_out), np.concatenate(act_out),
                  np.zeros(sum(a.size for a in act_out), np.float32), np.concatenate(sc_out), np.concatenate(tg_out))
    stats = RolloutStats(len(scenarios), n_l, n_e, harmed_l / n_l if n_l else float("nan"),
                         harmed_e / n_e if n_e else float("nan"), harm_world / max(n_worlds, 1),
                         int(data.actions.size), time.perf_counter() - t0)
    return data, stats


def _sum_stats(stats: Sequence[RolloutStats]) -> RolloutStats:
    """Rollout stats of several pools as one (rates weighted by agents, harm by worlds)."""
    n_l = sum(s.learner_agents for s in stats)
    n_e = sum(s.expert_agents for s in stats)
    n_s = sum(s.scenarios for s in stats)

    def rate(attr: str, n: int, weight: str) -> float:
        return sum(getattr(s, attr) * getattr(s, weight) for s in stats if getattr(s, weight)) / n if n \
            else float("nan")

    return RolloutStats(n_s, n_l, n_e, rate("learner_harm_rate", n_l, "learner_agents"),
                        rate("expert_harm_rate", n_e, "expert_agents"), rate("harm_per_world", n_s, "scenarios"),
                        sum(s.samples for s in stats), sum(s.seconds for s in stats))


def aggregate(parts: Sequence[BCData]) -> BCData:
    """Concatenate sample sets (DAgger's aggregation: every round's data is kept)."""
    parts = [p for p in parts if p is not None]
    if not parts:
        raise ValueError("parts: nothing to aggregate")
    if len({p.targets is None for p in parts}) > 1:
        raise ValueError("parts: some sample sets have targets and some do not")
    return BCData(*(None if getattr(parts[0], f.name) is None else np.concatenate([getattr(p, f.name) for p in parts])
                    for f in dataclasses.fields(BCData)))


@dataclasses.dataclass(frozen=True)
class DaggerConfig:
    """DAgger schedule: round r drives with ``betas[r]`` (round 0 must be 1: expert only),
    trains ``first_epochs`` epochs from scratch after round 0 and ``round_epochs`` epochs
    (warm start) on the aggregate after every later round."""

    betas: tuple[float, ...] = (1.0, 0.5, 0.0, 0.0)
    first_epochs: int = 6
    round_epochs: int = 3
    noise: float = 0.1
    ego_replay: float = 0.5
    keep: float = 1.0
    num_worlds: int = 64
    max_agents: int = 128
    coplayers: str = "controllable"

    def __post_init__(self) -> None:
        if not self.betas or self.betas[0] != 1.0 or any(not 0.0 <= b <= 1.0 for b in self.betas):
            raise ValueError(f"DaggerConfig.betas: need values in [0, 1] starting with 1.0, got {self.betas}")
        if self.first_epochs < 1 or self.round_epochs < 1:
            raise ValueError("DaggerConfig: first_epochs and round_epochs must be >= 1")


def _groups(scenarios: Sequence[Any]) -> list[list[Any]]:
    """A pool, or a list of pools (each simulated with its own slot count)."""
    from cpsim.scenario.datatypes import Scenario

    items = list(scenarios)
    if items and all(isinstance(x, Scenario) for x in items):
        return [items]
    groups = [list(g) for g in items]
    if not groups or any(not g or not all(isinstance(x, Scenario) for x in g) for g in groups):
        raise ValueError("scenarios: expected a non-empty pool of cpsim.Scenario or a list of such pools")
    return groups


def dagger(scenarios: Sequence[Any], config: DaggerConfig | None = None, train_config: TrainConfig | None = None,
           seed: int = 0, log: bool = False, checkpoint: str | os.PathLike | None = None,
           meta: dict[str, Any] | None = None) -> tuple[BCPolicy, list[dict[str, Any]]]:
    """Train a traffic model by DAgger against :class:`cpsim.expert.TrackingExpert`.

    ``scenarios``: a pool, or a list of pools (procedural logs and WOMD scenes): each pool
    gets its own simulator with ``min(config.max_agents, most agents present at t0)``
    slots, as the evaluator sizes its worlds. Round 0 drives with the expert (plus
    ``noise``) and fits a fresh model; every later round drives with the current model
    for a share ``1 - beta`` of the task vehicles (:func:`traffic_rollouts`), relabels the
    visited states with the expert, aggregates them with every earlier round's samples
    and continues training. ``checkpoint``: the model is saved there after every round
    (meta ``dagger_round``). Returns the model and one record per round (rollout stats
    summed over the pools, samples, accuracies).
    """
    dc = config or DaggerConfig()
    tc = train_config or TrainConfig()
    from cpsim.config import SimConfig
    from cpsim.model import Model
    from cpsim.observation import ObsLayout

    cfg = SimConfig().replace(goal_criterion="evaluation")
    groups = _groups(scenarios)
    pools = [Model(g, cfg) for g in groups]  # road grids built once for every round
    slots = [int(min(dc.max_agents, max(max(int(sc.log_valid[:, 0].sum()) for sc in g), 1))) for g in groups]
    offsets = np.cumsum([0] + [len(g) for g in groups])
    sl = ObsLayout(num_partners=cfg.num_partners, num_road=cfg.num_road).condition
    cond = (int(sl.start), int(sl.stop))
    num_actions = int(cfg.num_actions)
    parts: list[BCData] = []
    model: BCPolicy | None = None
    history: list[dict[str, Any]] = []
    for r, beta in enumerate(dc.betas):
        datas, stats_list = [], []
        for g, pool in enumerate(pools):
            d, st = traffic_rollouts(pool, model, beta, num_worlds=dc.num_worlds, max_agents=slots[g],
                                     seed=seed + 1000 * r + g, noise=dc.noise if r == 0 else 0.0,
                                     ego_replay=dc.ego_replay, keep=dc.keep, coplayers=dc.coplayers,
                                     progress=log)
            d.scenario = d.scenario + offsets[g]  # unique scenario ids across pools (validation split)
            datas.append(d)
            stats_list.append(st)
        data, stats = aggregate(datas), _sum_stats(stats_list)
        parts.append(data)
        agg = aggregate(parts)
        t1 = time.perf_counter()
        epochs = dc.first_epochs if model is None else dc.round_epochs
        model, metrics = train(agg, num_actions, cond, dataclasses.replace(tc, epochs=epochs, seed=tc.seed + r),
                               log=log, init=model, dynamics=cfg.dynamics, dt=float(cfg.dt))
        record = {"round": r, "beta": beta, **dataclasses.asdict(stats),
                  "pools": [dataclasses.asdict(st) for st in stats_list] if len(pools) > 1 else None,
                  "aggregate_samples": int(agg.actions.size),
                  "train_seconds": time.perf_counter() - t1, **{k: metrics[k] for k in
                                                                ("train_accuracy", "val_accuracy",
                                                                 "val_majority_accuracy")}}
        history.append(record)
        if log:
            print(json.dumps(record), file=sys.stderr)
        model.meta = {**(meta or {}), "dagger_round": r, "dagger": history}
        if checkpoint is not None:
            model.save(checkpoint)
    return model, history
