"""Imitation warm start of a recurrent self-play policy from the tracking expert (DAgger).

RL from scratch on the jerk model spends millions of transitions learning to stay on the
road. :func:`imitate_expert` gives a :class:`sb3_contrib.RecurrentPPO` (or CounterPlay)
policy that skill first: it rolls the policy out in self-play on its own training pool,
with conditions drawn from p_train as in the anchor recipe, labels every visited state
with :class:`cpsim.expert.TrackingExpert`'s action, and trains the actor by cross-entropy
on whole episodes (the LSTM runs from a zero memory at the episode start, exactly as in
the rollout). DAgger rounds shift the data from the expert's states (round 0 drives with
the expert) to the policy's own (later rounds drive with the policy with probability
1 - beta), so the policy learns to recover from its own mistakes. The critic is fitted to
the discounted conditioned returns of the same episodes, so PPO fine-tuning starts with
a value function that matches the policy instead of destroying it in its first updates.

Shapes: T = episode steps, N = worlds x agent slots, D = observation size.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, Sequence

import numpy as np
import torch as th
import torch.nn.functional as F

from cpalgo.common.policy_utils import actor_logits, critic_values, policy_step_logits, zero_states
from cpsim.conditions import sample_conditions
from cpsim.config import Controller, known_fields
from cpsim.envs.selfplay import OBS_BOUND
from cpsim.expert import EXPERTS, actions_under

#: Imitation teachers by name (cpsim.expert.make_expert).
TEACHERS: tuple[str, ...] = EXPERTS

__all__ = ["TEACHERS", "ImitationConfig", "EpisodeBatch", "collect_episodes", "imitation_losses",
           "train_on_episodes", "imitate_expert"]


@dataclasses.dataclass(frozen=True)
class ImitationConfig:
    """DAgger schedule and optimiser settings.

    Attributes:
        iterations: DAgger rounds (each collects ``episodes`` batches of worlds).
        episodes: batches of ``num_worlds`` episodes collected per round.
        num_worlds: worlds simulated together.
        beta: probability that the expert drives in round 0; round i uses beta * decay^i.
        decay: per-round factor of beta.
        keep_rounds: rounds of data kept for training (the newest ones).
        epochs: passes over the kept data per round.
        batch_sequences: episodes (agent slots) per gradient step.
        learning_rate: Adam step size.
        value_coef: weight of the critic's regression loss.
        gamma: discount of the critic's return targets.
        max_grad_norm: gradient clipping.
        teacher: ``"tracking"`` (:class:`cpsim.expert.TrackingExpert`, follows its log and
            ignores other vehicles, one behaviour for every condition) or ``"reactive"``
            (:class:`cpsim.expert.ReactiveExpert`, keeps gaps, yields at crossings, and drives
            faster or slower with each agent's condition).
        style_pairs: extra labelled copies of every episode, each with every agent's style
            fields swapped for those of a random profile of the CounterPlay panel (task fields
            kept): the same visited states, the swapped condition in the observation, and the
            teacher's action under it. The student then sees states that differ only in the
            style, which is what a search from a root varies; without them it sees each
            state under one condition and learns a style effect several times weaker than
            the teacher's. The critic is
            fitted on the original copy only (the swapped return is not observed).
    """

    iterations: int = 6
    episodes: int = 1
    num_worlds: int = 64
    beta: float = 1.0
    decay: float = 0.5
    keep_rounds: int = 3
    epochs: int = 10
    batch_sequences: int = 32
    learning_rate: float = 1e-3
    value_coef: float = 0.5
    gamma: float = 0.99
    max_grad_norm: float = 0.5
    teacher: str = "tracking"
    style_pairs: int = 0

    def __post_init__(self) -> None:
        if self.teacher not in TEACHERS:
            raise ValueError(f"ImitationConfig.teacher: unknown teacher {self.teacher!r}; accepted: {list(TEACHERS)}")
        for name in ("iterations", "episodes", "num_worlds", "keep_rounds", "epochs", "batch_sequences"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"ImitationConfig.{name}: must be an integer >= 1, got {value!r}")
        if not isinstance(self.style_pairs, (int, np.integer)) or self.style_pairs < 0:
            raise ValueError(f"ImitationConfig.style_pairs: must be an integer >= 0, got {self.style_pairs!r}")
        if self.style_pairs and self.teacher == "tracking":
            raise ValueError("ImitationConfig.style_pairs: the tracking teacher ignores the style, so its swapped "
                             "labels would teach the student to ignore it too; use a reactive teacher")
        for name in ("beta", "decay", "gamma"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"ImitationConfig.{name}: must be in [0, 1], got {value!r}")
        for name in ("learning_rate", "max_grad_norm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ImitationConfig.{name}: must be > 0, got {getattr(self, name)!r}")
        if self.value_coef < 0:
            raise ValueError(f"ImitationConfig.value_coef: must be >= 0, got {self.value_coef!r}")

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "ImitationConfig":
        return cls(**known_fields(cls, values, "ImitationConfig"))


@dataclasses.dataclass
class EpisodeBatch:
    """Whole self-play episodes of N agent slots, time-major.

    Attributes:
        obs: (T, N, D) float32 observations as the policy saw them (zero when inactive).
        labels: (T, N) int64 expert actions.
        mask: (T, N) bool, the slot held a live POLICY agent at that step.
        returns: (T, N) float32 discounted conditioned return from that step on.
        agreement: share of masked steps where the policy's argmax equals the label.
        value_mask: (T, N) bool, the steps the critic is fitted on (``None``: ``mask``);
            style-swapped copies (``style_pairs``) have none.
    """

    obs: th.Tensor
    labels: th.Tensor
    mask: th.Tensor
    returns: th.Tensor
    agreement: float
    value_mask: th.Tensor | None = None


def _policy_obs(sim) -> th.Tensor:
    obs = sim.obs.reshape(sim.num_worlds * sim.max_agents, -1).clamp(-OBS_BOUND, OBS_BOUND)
    return obs * sim.policy_mask.reshape(-1, 1)


@th.no_grad()
def collect_episodes(policy, sim, expert, beta: float, rng: np.random.Generator,
                     gamma: float = 0.99, condition: np.ndarray | None = None,
                     style_pairs: int = 0) -> EpisodeBatch:
    """Run one episode in every world of ``sim`` and label it with the expert.

    Every POLICY agent follows the expert with probability ``beta`` per episode (a
    per-agent coin, so rounds mix expert and policy agents in the same worlds) and its
    own sampled action otherwise. Conditions are drawn from p_train per agent, or are the
    fixed raw ``condition`` (10,) for every agent when one is given. With ``style_pairs``
    K > 0 the batch holds N (K + 1) slots: the episodes as driven, then K copies whose
    observations carry a style-swapped condition (:class:`ImitationConfig`) and whose
    labels are the expert's actions under it at the same states.
    """
    W, A = sim.num_worlds, sim.max_agents
    N = W * A
    pool = rng.integers(0, sim.num_scenarios, size=W)
    conds = sample_conditions(rng, (W, A)) if condition is None else np.broadcast_to(condition, (W, A, len(condition)))
    sim.reset(scenario_index=pool, conditions=conds)
    swapped = [_swap_styles(conds, rng) for _ in range(style_pairs)]
    T = sim.config.episode_steps
    device = policy.device
    states = zero_states(policy, N, device)
    by_expert = th.as_tensor(rng.random(N) < beta)
    obs_buf = th.zeros((T, N * (1 + style_pairs), sim.obs_layout.size), dtype=th.float32)
    labels = th.zeros((T, N * (1 + style_pairs)), dtype=th.int64)
    mask = th.zeros((T, N), dtype=th.bool)
    rewards = th.zeros((T, N), dtype=th.float32)
    agree = 0
    starts = th.ones(N, device=device)
    for t in range(T):
        live = ((sim.controllers == int(Controller.POLICY)) & sim.alive).reshape(-1).clone()
        obs = _policy_obs(sim)
        logits, _, states = policy_step_logits(policy, obs.to(device), states, starts)
        starts = th.zeros(N, device=device)
        label = expert.actions().reshape(-1).long()
        sampled = th.distributions.Categorical(logits=logits).sample().cpu()
        agree += int(((logits.argmax(-1).cpu() == label) & live).sum())
        action = th.where(by_expert, label, sampled)
        obs_buf[t, :N] = obs
        labels[t, :N] = label
        mask[t] = live
        for k, cond_k in enumerate(swapped, start=1):  # the world drives on under its own conditions
            labels[t, k * N:(k + 1) * N] = actions_under(expert, cond_k).reshape(-1).long()
            obs_buf[t, k * N:(k + 1) * N] = sim.obs_layout.replace_condition(obs, cond_k.reshape(N, -1)) \
                * live.reshape(-1, 1)
        sim.step(action.reshape(W, A).to(th.int32))
        rewards[t] = sim.reward.reshape(-1) * live
        if bool(sim.world_done.all()):
            obs_buf, labels, mask, rewards = obs_buf[: t + 1], labels[: t + 1], mask[: t + 1], rewards[: t + 1]
            break
    returns = th.zeros_like(rewards)
    running = th.zeros(N)
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = rewards[t] + gamma * running * mask[t]
        returns[t] = running
    n = max(int(mask.sum()), 1)
    if not swapped:
        return EpisodeBatch(obs_buf, labels, mask, returns, agree / n)
    copies = 1 + style_pairs
    return EpisodeBatch(obs_buf, labels, mask.repeat(1, copies), returns.repeat(1, copies), agree / n,
                        value_mask=th.cat([mask, th.zeros_like(mask).repeat(1, style_pairs)], 1))


def _swap_styles(conditions: np.ndarray, rng: np.random.Generator) -> th.Tensor:
    """Raw conditions (W, A, 10) whose style fields are those of a random panel profile per
    agent (task fields kept), as a float32 tensor."""
    from cpsim.conditions import PANEL, with_panel_styles

    return th.as_tensor(with_panel_styles(conditions, rng.integers(0, len(PANEL), size=conditions.shape[:-1])))


def _sequence_forward(policy, obs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """Logits (T, B, n_actions) and values (T, B) of whole episodes from a zero memory."""
    T, B, D = obs.shape
    flat = obs.swapaxes(0, 1).reshape(B * T, D)  # sequence-major, as sb3-contrib expects
    states = zero_states(policy, B, obs.device)
    starts = th.zeros(B * T, device=obs.device)
    starts[::T] = 1.0
    logits = actor_logits(policy, flat, states.pi, starts)[0]
    values = critic_values(policy, flat, states.vf, starts)
    return logits.reshape(B, T, -1).swapaxes(0, 1), values.reshape(B, T).swapaxes(0, 1)


def imitation_losses(policy, obs: th.Tensor, labels: th.Tensor, mask: th.Tensor,
                     returns: th.Tensor, value_mask: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
    """Masked cross-entropy of the actor and mean squared error of the critic.

    Args:
        obs: (T, B, D); labels, mask, returns: (T, B).
        value_mask: (T, B) bool, the steps of the critic's loss (default: ``mask``).
    """
    logits, values = _sequence_forward(policy, obs)
    m = mask.float()
    n = m.sum().clamp(min=1.0)
    ce = (F.cross_entropy(logits.reshape(-1, logits.shape[-1]), labels.reshape(-1), reduction="none")
          * m.reshape(-1)).sum() / n
    vm = m if value_mask is None else value_mask.float()
    mse = (((values - returns) ** 2) * vm).sum() / vm.sum().clamp(min=1.0)
    return ce, mse


def train_on_episodes(policy, optimizer: th.optim.Optimizer, data: Sequence[Any],
                      losses: Callable[[Any, th.Tensor], tuple[th.Tensor, th.Tensor]], epochs: int,
                      batch_sequences: int, generator: th.Generator, value_coef: float,
                      max_grad_norm: float) -> tuple[float, float]:
    """Minibatch passes over kept rounds of whole episodes (imitation and distillation).

    Every epoch visits the rounds in order, each in a fresh random order of its agent slots
    that hold at least one live step, ``batch_sequences`` slots per minibatch; the update
    minimises ``main + value_coef * value`` with the gradient norm clipped.

    Args:
        data: rounds with a (T, N) bool ``mask``.
        losses: ``losses(round, slot_indices) -> (main_loss, value_loss)``.
    Returns:
        the mean main and value losses over the last epoch's minibatches.
    """
    main_sum = value_sum = 0.0
    steps = 0
    for _ in range(epochs):
        main_sum = value_sum = 0.0  # the caller reports the last epoch's training losses
        steps = 0
        for batch in data:
            keep = th.nonzero(batch.mask.any(0)).reshape(-1)
            order = keep[th.randperm(keep.numel(), generator=generator)]
            for lo in range(0, order.numel(), batch_sequences):
                main, value = losses(batch, order[lo:lo + batch_sequences])
                loss = main + value_coef * value
                optimizer.zero_grad()
                loss.backward()
                th.nn.utils.clip_grad_norm_(policy.parameters(), max_grad_norm)
                optimizer.step()
                main_sum += main.item()
                value_sum += value.item()
                steps += 1
    return main_sum / max(steps, 1), value_sum / max(steps, 1)


def imitate_expert(model, scenarios: Sequence[Any] | None = None, config: ImitationConfig | None = None,
                   sim_config: Any = None, seed: int = 0,
                   log: Callable[[str], None] | None = print) -> list[dict[str, float]]:
    """DAgger warm start of ``model.policy`` from the teacher ``config.teacher``.

    Args:
        model: a RecurrentPPO-family model with a discrete action space whose env is a
            :class:`cpsim.SelfPlayVecEnv` (its scenarios, slots and dynamics are used
            unless ``scenarios`` / ``sim_config`` are given).
        scenarios: training scenarios (default: the env's pool).
        config: the DAgger schedule.
        sim_config: SimConfig for the rollouts (default: the env's simulator config).
        seed: seed of scenario, condition and coin draws.
        log: called with one line per round (None: silent).
    Returns:
        one dict per round: beta, agreement (argmax = expert before training on the round),
        cross_entropy, value_mse (mean training losses of the round's last epoch), transitions, seconds.
    """
    from cpsim.expert import make_expert
    from cpsim.simulator import Simulator

    cfg = config or ImitationConfig()
    env = model.get_env()
    inner = getattr(env, "venv", env)
    while hasattr(inner, "venv") and not hasattr(inner, "sim"):
        inner = inner.venv
    base_sim = getattr(inner, "sim", None)
    if scenarios is None:
        if base_sim is None:
            raise ValueError("scenarios: the model's env is not a SelfPlayVecEnv; pass scenarios")
        scenarios = base_sim.scenarios
    scenarios = list(scenarios)
    if not scenarios:
        raise ValueError("scenarios: empty")
    max_agents = base_sim.max_agents if base_sim is not None else 8
    if sim_config is None and base_sim is not None:
        sim_config = base_sim.config
    sim = Simulator(scenarios, num_worlds=cfg.num_worlds, max_agents=max_agents, config=sim_config, seed=seed)
    if model.observation_space.shape != (sim.obs_layout.size,):
        raise ValueError(f"model: observation shape {model.observation_space.shape} does not match the "
                         f"simulator's ({sim.obs_layout.size},)")
    expert = make_expert(cfg.teacher, sim)
    # an env trained under one fixed condition imitates under that condition too
    fixed = getattr(inner, "fixed_condition", None)
    rng = np.random.default_rng(seed)
    policy = model.policy
    optimizer = th.optim.Adam(policy.parameters(), lr=cfg.learning_rate)
    data: list[EpisodeBatch] = []
    history: list[dict[str, float]] = []
    gen = th.Generator().manual_seed(seed)
    for it in range(cfg.iterations):
        t0 = time.perf_counter()
        beta = cfg.beta * cfg.decay ** it
        policy.set_training_mode(False)
        new = [collect_episodes(policy, sim, expert, beta, rng, cfg.gamma, fixed, cfg.style_pairs)
               for _ in range(cfg.episodes)]
        data.extend(new)
        data = data[-cfg.keep_rounds * cfg.episodes:]
        agreement = float(np.mean([b.agreement for b in new]))
        policy.set_training_mode(True)

        def losses(batch: EpisodeBatch, idx: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
            dev = policy.device
            vmask = None if batch.value_mask is None else batch.value_mask[:, idx].to(dev)
            return imitation_losses(policy, batch.obs[:, idx].to(dev), batch.labels[:, idx].to(dev),
                                    batch.mask[:, idx].to(dev), batch.returns[:, idx].to(dev), vmask)

        ce_mean, mse_mean = train_on_episodes(policy, optimizer, data, losses, cfg.epochs, cfg.batch_sequences,
                                              gen, cfg.value_coef, cfg.max_grad_norm)
        policy.set_training_mode(False)
        row = {"round": it, "beta": beta, "agreement": agreement, "cross_entropy": ce_mean,
               "value_mse": mse_mean,
               "transitions": int(sum(int(b.mask.sum()) for b in new)) // (1 + cfg.style_pairs),
               "seconds": time.perf_counter() - t0}
        history.append(row)
        if log is not None:
            log(f"imitation round {it}: beta {beta:.3f}  agreement {agreement:.1%}  "
                f"cross-entropy {row['cross_entropy']:.3f}  value mse {row['value_mse']:.4f}  "
                f"{row['transitions']} transitions  {row['seconds']:.0f} s")
    return history
