"""PlannerRFT adapted to recurrent self-play driving (the seed paper's PlannerRFT-dagger).

The original (Li et al., 2026) fine-tunes a diffusion planner with reinforcement learning:
for each scene it samples a group of trajectories, scores them closed-loop against
log-replayed surrounding vehicles, and trains the planner with a clipped group-relative
(GRPO-style) trajectory objective. A separate exploration policy, trained by PPO, sets
the guidance scale of the denoiser per rollout so that the group explores usefully.

Adaptation (:class:`PlannerRFT`): a scene is an interaction state of the main self-play
rollout (:mod:`cpalgo.baselines.continuations`), a trajectory one of ``group_size`` (1 + 5)
continuations of the focal agent to the original deadline. In every continuation the
other agents follow their logs from the root on (controller REPLAY: they are placed on
their logged poses and do not react), which is the original's traffic assumption. Our
categorical policy has no denoiser, so the small learned :class:`ExplorationHead` sets the
*sampling temperature* of each continuation instead: ``x ~ N(mu(o_root), sigma)``,
temperature ``exp(clip(x, log t_min, log t_max))``, and PPO trains the head on the
continuation's group-normalised return (clipped surrogate, its own Adam optimiser, after
each update). The planner keeps the clipped group-relative objective: group-normalised
discounted returns as advantages, the ratio of the current to the sampling policy (without
temperature) clipped to ``1 +- clip_range``, averaged over each continuation's decisions
and then over continuations (GRPO's sample-level mean), added with weight ``group_coef`` to
``extra_minibatches`` PPO minibatch updates. The main self-play PPO stays as it is.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch as th

from cpalgo.baselines.continuations import (
    ContinuationPPO,
    ContinuationRoot,
    GroupJob,
    GroupResult,
    collate_continuations,
    continuation_logits,
    group_normalized,
)
from cpalgo.baselines.plannerrft.policies import ExplorationHead
from cpalgo.common.hooked_train import check_number

__all__ = ["PlannerRFT", "grpo_objective"]


def grpo_objective(logp: th.Tensor, logp_old: th.Tensor, advantages: th.Tensor, mask: th.Tensor,
                   clip_range: float) -> th.Tensor:
    """GRPO's clipped surrogate (to maximise): per continuation the mean over its decisions
    of ``min(r A, clip(r, 1 - eps, 1 + eps) A)``, then the mean over continuations.

    Args: logp, logp_old, mask: (K, T); advantages: (K,). Returns a scalar.
    """
    ratio = th.exp(logp - logp_old)
    adv = advantages[:, None]
    surrogate = th.min(ratio * adv, th.clamp(ratio, 1.0 - clip_range, 1.0 + clip_range) * adv)
    m = mask.float()
    per = (surrogate * m).sum(1) / m.sum(1).clamp(min=1.0)
    has = m.sum(1) > 0
    return per[has].mean() if bool(has.any()) else per.sum() * 0.0


class PlannerRFT(ContinuationPPO):
    """PlannerRFT-dagger (see the module docstring).

    Args:
        temperature_min, temperature_max: range of the continuation temperature
            (0.5, 2.0; 0 < min <= 1 <= max).
        head_hidden: width of the exploration head (32).
        head_init_std: initial std of the log temperature (0.3).
        head_lr: Adam step of the exploration head (1e-3).
        head_epochs: PPO epochs of the head per generation (4).
        head_clip: PPO clip of the head (0.2).
        Other arguments: :class:`cpalgo.baselines.continuations.ContinuationPPO`'s and PPO's.

    Attributes:
        exploration_head: the :class:`ExplorationHead` (saved with the model).
        continuation_totals: also ``head_updates`` and ``temperature_sum`` (summed over
            continuations; divide by ``continuations`` for the mean).
    """

    traffic_mode: ClassVar[str] = "replay"
    _RUNTIME_ATTRS: ClassVar[tuple[str, ...]] = ContinuationPPO._RUNTIME_ATTRS + ("_head_data",)

    def __init__(self, policy: Any, env: Any, temperature_min: float = 0.5, temperature_max: float = 2.0,
                 head_hidden: int = 32, head_init_std: float = 0.3, head_lr: float = 1e-3, head_epochs: int = 4,
                 head_clip: float = 0.2, **kwargs: Any) -> None:
        self.temperature_min = temperature_min
        self.temperature_max = temperature_max
        self.head_hidden = head_hidden
        self.head_init_std = head_init_std
        self.head_lr = head_lr
        self.head_epochs = head_epochs
        self.head_clip = head_clip
        self.exploration_head: ExplorationHead | None = None
        self.head_optimizer: th.optim.Optimizer | None = None
        super().__init__(policy, env, **kwargs)

    def _validate_settings(self) -> None:
        super()._validate_settings()
        check_number("temperature_min", self.temperature_min, low=0.0, high=1.0, low_open=True)
        check_number("temperature_max", self.temperature_max, low=1.0)
        check_number("head_hidden", self.head_hidden, low=1, integer=True)
        check_number("head_init_std", self.head_init_std, low=0.0, low_open=True)
        check_number("head_lr", self.head_lr, low=0.0, low_open=True)
        check_number("head_epochs", self.head_epochs, low=1, integer=True)
        check_number("head_clip", self.head_clip, low=0.0, high=1.0, low_open=True, high_open=True)

    def _reset_runtime(self) -> None:
        super()._reset_runtime()
        self._head_data: dict[str, th.Tensor] | None = None

    def _setup_model(self) -> None:
        super()._setup_model()
        if self.exploration_head is None:
            th.manual_seed(int(self.seed or 0) + 7368787)
            self.exploration_head = ExplorationHead(int(self.observation_space.shape[0]), int(self.head_hidden),
                                                    float(self.head_init_std)).to(self.device)
            self.head_optimizer = th.optim.Adam(self.exploration_head.parameters(), lr=float(self.head_lr))

    # ------------------------------------------------------------------ groups
    def _root_obs(self, roots: list[ContinuationRoot]) -> th.Tensor:
        """(n, D) focal observations at the roots, read from the rollout buffer."""
        obs = self.rollout_buffer.observations  # (n_steps, n_envs, D), not flattened yet
        rows = np.array([[r.buffer_pos, r.env_index] for r in roots], np.int64)
        return th.as_tensor(np.asarray(obs[rows[:, 0], rows[:, 1]], np.float32), device=self.device)

    def _group_jobs(self, roots: list[ContinuationRoot]) -> list[GroupJob]:
        assert self.exploration_head is not None
        g = int(self.group_size)
        obs = self._root_obs(roots)
        with th.no_grad():
            dist = self.exploration_head(obs)
            x = dist.sample((g,)).T  # (n, G)
            logp = dist.log_prob(x.T).T
        lo, hi = math.log(float(self.temperature_min)), math.log(float(self.temperature_max))
        temperature = x.clamp(lo, hi).exp().cpu().numpy()
        data = {"obs": obs, "x": x, "logp": logp}
        if self._head_data is None:
            self._head_data = data
        else:  # a later wave of the same generation
            self._head_data = {k: th.cat([self._head_data[k], v]) for k, v in data.items()}
        self._bump("temperature_sum", float(temperature.sum()))
        return [GroupJob(root=r, traffic=["replay"] * g, temperature=temperature[i]) for i, r in enumerate(roots)]

    def _before_gae(self) -> None:
        self._head_data = None
        super()._before_gae()

    def _use_groups(self, roots: list[ContinuationRoot], results: list[GroupResult]) -> None:
        returns = np.stack([res.returns for res in results])  # (n, G)
        advantages = group_normalized(returns)
        self._group_batch = collate_continuations(roots, results, list(advantages), device=self.device)
        if self._head_data is not None:
            self._head_data["advantages"] = th.as_tensor(advantages, device=self.device)

    def _generation_terms(self, clip_range: float) -> dict[str, th.Tensor]:
        batch = self._group_batch
        assert batch is not None
        logits = continuation_logits(self.policy, batch)
        logp = th.log_softmax(logits, -1).gather(-1, batch.actions[..., None]).squeeze(-1)
        objective = grpo_objective(logp, batch.logp_old, batch.advantages, batch.mask, float(clip_range))
        return {"grpo_loss": -float(self.group_coef) * objective}

    # ------------------------------------------------------------------ exploration head
    def _train_head(self) -> None:
        """PPO on the head: action x (log temperature), advantage the group-normalised return."""
        data = self._head_data
        self._head_data = None
        if data is None or "advantages" not in data or self.exploration_head is None:
            return
        head, opt = self.exploration_head, self.head_optimizer
        assert opt is not None
        adv = data["advantages"]
        clip = float(self.head_clip)
        losses = []
        for _ in range(int(self.head_epochs)):
            dist = head(data["obs"])
            logp = dist.log_prob(data["x"].T).T
            ratio = th.exp(logp - data["logp"])
            loss = -th.min(ratio * adv, th.clamp(ratio, 1 - clip, 1 + clip) * adv).mean()
            opt.zero_grad()
            loss.backward()
            th.nn.utils.clip_grad_norm_(head.parameters(), self.max_grad_norm)
            opt.step()
            losses.append(float(loss.item()))
        self._bump("head_updates", int(self.head_epochs))
        self.logger.record("train/exploration_head_loss", float(np.mean(losses)))
        self.logger.record("train/exploration_log_std", float(head.log_std.item()))

    def _after_train(self) -> None:
        self._train_head()
        super()._after_train()
