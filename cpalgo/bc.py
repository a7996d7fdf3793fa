"""Behaviour-cloning log-imitation traffic model (stands in for SMART in the evaluation).

Data: the training pool's logs. Every agent is put on log replay; at each step the
simulator's observation of every controllable vehicle whose log is valid at ``t`` and
``t + H`` is a sample, and its label is the discrete action (default: the 12-action
jerk set) that, held for ``H`` steps (default 5, 0.5 s), best reproduces the logged state
``H`` steps ahead from the agent's current simulator state. A second pass (``mode="track"``,
on by default in the command) drives the controllable agents with those labels plus
random actions, so the data also covers states off the log, labelled with the action that
returns to it (plain behaviour cloning otherwise drifts off the road in closed loop).

The label is found with the simulator's own dynamics: the current state of the chunk's
worlds is restored into a probe simulator holding one copy per action (one-to-many
:meth:`cpsim.Simulator.restore`), every copy holds its action for ``H`` steps, and the
action whose pose is then closest to the log wins (position error plus heading and speed
errors scaled to metres). No Python loop over agents or worlds.

Model: a small MLP (torch) over the observation with the condition slice zeroed (traffic
does not read reward conditions). It is an SB3-compatible co-player:
``predict(obs, state, episode_start, deterministic) -> (actions, None)``, and is saved as
a small ``.pt`` file (float16 weights).

Command (the shipped ``zoo/bc_traffic.pt``; its ``meta`` records the command and accuracies)::

    python -m cpalgo.bc --out zoo/bc_traffic.pt --scenarios 60 --worlds 30 --max-agents 32 \
        --mode both --noise 0.2 --hidden 256 --weight-decay 1e-3 --epochs 8
"""

from __future__ import annotations

import argparse
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

from cpsim.atomic import atomic_path

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
class BCPolicy(nn.Module):
    """MLP classifier over observations -> action logits (discrete action set).

    Args:
        obs_size: D, the simulator's observation size.
        num_actions: size of the action set (12 for the jerk model).
        hidden: hidden layer widths.
        condition_slice: (start, stop) of the reward-condition slice in the observation;
            zeroed before the MLP so the model ignores conditions.
        obs_scale: (D,) per-feature scale the input is divided by (from the training data).
    """

    def __init__(self, obs_size: int, num_actions: int, hidden: Sequence[int] = (128, 128),
                 condition_slice: tuple[int, int] | None = None, obs_scale: np.ndarray | None = None,
                 meta: dict[str, Any] | None = None):
        super().__init__()
        if obs_size < 1 or num_actions < 2:
            raise ValueError(f"obs_size must be >= 1 and num_actions >= 2, got {obs_size}, {num_actions}")
        self.obs_size = int(obs_size)
        self.num_actions = int(num_actions)
        self.hidden = tuple(int(h) for h in hidden)
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
        layers.append(nn.Linear(width, self.num_actions))
        self.net = nn.Sequential(*layers)
        self.meta = dict(meta or {})

    def forward(self, obs: th.Tensor) -> th.Tensor:
        """(n, D) observations -> (n, num_actions) logits."""
        return self.net(obs * self.input_gain)

    # SB3-compatible co-player interface --------------------------------------------
    @th.no_grad()
    def predict(self, observation: np.ndarray, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, None]:
        """SB3's signature. Deterministic: argmax; else a sample. Stateless (state None)."""
        obs = th.as_tensor(np.asarray(observation, np.float32)).reshape(-1, self.obs_size)
        logits = self.forward(obs)
        if deterministic:
            act = logits.argmax(-1)
        else:
            act = th.distributions.Categorical(logits=logits).sample()
        return act.numpy().astype(np.int64), None

    # persistence ---------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Write the checkpoint atomically (temp file + ``os.replace``), weights in float16."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "format": "cpalgo.bc", "version": FORMAT_VERSION, "obs_size": self.obs_size,
            "num_actions": self.num_actions, "hidden": list(self.hidden),
            "condition_slice": self.condition_slice, "meta": self.meta,
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
                    payload["condition_slice"], meta=payload.get("meta"))
        model.load_state_dict({k: v.float() for k, v in payload["state_dict"].items()})
        model.eval()
        return model


# ============================================================================ data
@dataclasses.dataclass
class BCData:
    """Samples for behaviour cloning: ``obs`` (n, D) float32, ``actions`` (n,) int64,
    ``error_m`` (n,) float32 the label's reproduction error (m), ``scenario`` (n,) int64."""

    obs: np.ndarray
    actions: np.ndarray
    error_m: np.ndarray
    scenario: np.ndarray


def _np(x: Any) -> np.ndarray:
    return x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)


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
        return BCData(*(np.concatenate([getattr(p, f.name) for p in parts])
                        for f in dataclasses.fields(BCData)))
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

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TrainConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        if set(d) - known:
            raise ValueError(f"TrainConfig: unknown keys {sorted(set(d) - known)}; known: {sorted(known)}")
        return cls(**d)

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.batch_size < 1 or self.lr <= 0 or not 0 <= self.val_fraction < 1:
            raise ValueError(f"TrainConfig: invalid values {self}")


def train(data: BCData, num_actions: int, condition_slice: tuple[int, int] | None = None,
          config: TrainConfig | None = None, log: bool = False) -> tuple[BCPolicy, dict[str, float]]:
    """Fit a :class:`BCPolicy` by cross-entropy; validation split by scenario (no leakage).

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
    scale = np.maximum(np.abs(data.obs[tr]).max(0), 1.0)  # features already ~[-1, 1]; guard outliers
    model = BCPolicy(data.obs.shape[1], num_actions, cfg.hidden, condition_slice, obs_scale=scale)
    x = th.as_tensor(data.obs)
    y = th.as_tensor(data.actions)
    xtr, ytr = x[th.as_tensor(tr)], y[th.as_tensor(tr)]
    opt = th.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = th.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=cfg.epochs)
    for epoch in range(cfg.epochs):
        model.train()
        perm = th.randperm(xtr.shape[0])
        total = 0.0
        for b in range(0, xtr.shape[0], cfg.batch_size):
            i = perm[b:b + cfg.batch_size]
            loss = nn.functional.cross_entropy(model(xtr[i]), ytr[i])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * i.numel()
        sched.step()
        if log:
            print(f"epoch {epoch + 1}/{cfg.epochs}: loss {total / max(xtr.shape[0], 1):.4f}", file=sys.stderr)
    model.eval()
    with th.no_grad():
        acc_tr = float((model(xtr).argmax(-1) == ytr).float().mean())
        if val.any():
            xv, yv = x[th.as_tensor(val)], y[th.as_tensor(val)]
            acc_v = float((model(xv).argmax(-1) == yv).float().mean())
            majority = int(np.bincount(data.actions[tr], minlength=num_actions).argmax())
            maj_v = float((yv == majority).float().mean())
        else:
            acc_v = maj_v = float("nan")
    metrics = {"train_accuracy": acc_tr, "val_accuracy": acc_v, "val_majority_accuracy": maj_v,
               "train_samples": int(tr.sum()), "val_samples": int(val.sum()),
               "label_error_m_mean": float(data.error_m.mean())}
    return model, metrics


# ============================================================================ command
def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m cpalgo.bc", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="checkpoint path (.pt), written atomically")
    p.add_argument("--scenarios", type=int, default=200, help="training-pool scenarios (procedural)")
    p.add_argument("--pool", default="procedural", help="'procedural' or a folder of WOMD JSON/.npz")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--worlds", type=int, default=32)
    p.add_argument("--max-agents", type=int, default=32)
    p.add_argument("--epochs", type=int, default=15)
    p.add_argument("--hidden", type=int, nargs="+", default=[128, 128])
    p.add_argument("--batch-size", type=int, default=512)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--weight-decay", type=float, default=1e-5)
    p.add_argument("--mode", choices=COLLECT_MODES, default="both",
                   help="replay: log-replay observations only; track: noisy log tracking; both")
    p.add_argument("--noise", type=float, default=0.2, help="random-action probability when tracking")
    p.add_argument("--lookahead", type=int, default=5, help="label lookahead, steps")
    args = p.parse_args(argv)
    if not str(args.out).endswith(".pt"):
        p.error("--out must end in .pt")
    if args.scenarios < 2:
        p.error("--scenarios must be >= 2")
    t0 = time.perf_counter()
    if args.pool == "procedural":
        from cpsim.scenario import train_pool

        scenarios = list(train_pool(args.scenarios, args.seed))
    else:
        if not Path(args.pool).is_dir():
            p.error(f"--pool: {args.pool!r} is neither 'procedural' nor a folder")
        from cpsim.scenario import load_dir

        loaded = load_dir(args.pool)
        scenarios = list(loaded[0] if isinstance(loaded, tuple) else loaded)[: args.scenarios]
    from cpsim.config import SimConfig

    data = collect(scenarios, args.worlds, args.max_agents, seed=args.seed, progress=True,
                   lookahead=args.lookahead, mode=args.mode, noise=args.noise)
    t1 = time.perf_counter()
    import cpsim

    probe = cpsim.Simulator(scenarios[:1], num_worlds=1, max_agents=args.max_agents)
    sl = probe.obs_layout.condition
    cond = (int(sl.start), int(sl.stop))
    model, metrics = train(data, SimConfig().num_actions, cond,
                           TrainConfig(hidden=tuple(args.hidden), epochs=args.epochs,
                                       batch_size=args.batch_size, lr=args.lr,
                                       weight_decay=args.weight_decay, seed=args.seed), log=True)
    metrics.update({"scenarios": len(scenarios), "pool": args.pool, "seed": args.seed,
                    "collect_seconds": t1 - t0, "train_seconds": time.perf_counter() - t1,
                    "command": "python -m cpalgo.bc " + " ".join(argv if argv is not None else sys.argv[1:])})
    model.meta = metrics
    path = model.save(args.out)
    print(json.dumps({"out": str(path), "bytes": path.stat().st_size, **metrics}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
