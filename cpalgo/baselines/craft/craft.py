"""CRAFT adapted to recurrent self-play driving (the seed paper's CRAFT-dagger baseline).

The original (Chen et al., 2026) fine-tunes a planner with a score-function (REINFORCE)
objective over a set of candidate plans per scene, with counterfactual advantages
normalised within the candidate group. Candidates are scored cheaply against a traffic
proxy (other vehicles hold their last controls, then the controls decay), a residual
correction learned from closed-loop rollouts under frozen co-players corrects the proxy's
bias, and an asymmetric KL toward an exponential moving average (EMA) of the policy keeps
the updates conservative.

Adaptation (:class:`CRAFT`): the scenes are interaction states of the main self-play
rollout and the candidates ``group_size`` (1 + 5) continuations of the recurrent
categorical policy to the original deadline (:mod:`cpalgo.baselines.continuations`).

* **Proxy candidates.** In ``group_size - residual_rollouts`` continuations the co-players
  are driven by :func:`cpalgo.baselines.craft.proxy.hold_then_decay` (last action held for
  ``proxy_hold`` decisions, then its components decay by ``proxy_decay`` per decision).
* **Residual correction.** The first ``residual_rollouts`` continuations run closed loop,
  co-players driving with the (frozen during the group) policy; closed-loop continuation
  ``i`` shares the focal agent's random draws with proxy continuation
  ``residual_rollouts + i``, so the pair differs by the traffic model. Their return gap is
  one sample of the proxy's residual; a running mean of it per proxy outcome (goal,
  collision, off-road, timeout; EMA with ``residual_decay``) corrects every proxy
  candidate's return: ``R~ = R_proxy + residual[outcome]``. Closed-loop candidates keep
  their own return.
* **Objective.** Advantages are the group-normalised corrected returns, and the loss is
  the score function ``-A_j * mean_t log pi(a_jt | s_jt)`` averaged over candidates (no
  ratio, no clip), weighted by ``group_coef``.
* **Asymmetric EMA KL.** ``kl_forward_coef`` x KL(pi_EMA || pi) + ``kl_reverse_coef`` x
  KL(pi || pi_EMA) over the candidates' decisions: the mass-covering direction keeps every
  action the EMA policy takes, the lighter mode-seeking direction lets the policy sharpen.
  The EMA (of every policy parameter, ``ema_decay`` per update, starting from the anchor)
  runs its actor LSTM from the same root memories.

Both terms join ``extra_minibatches`` PPO minibatch updates; the main self-play PPO stays.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch as th

from cpalgo.baselines.continuations import (
    ContinuationPPO,
    ContinuationRoot,
    GroupJob,
    GroupResult,
    ProxyFn,
    collate_continuations,
    continuation_logits,
    group_normalized,
)
from cpalgo.baselines.craft.proxy import hold_then_decay
from cpalgo.common.hooked_train import categorical_kl, check_number, masked_mean
from cpalgo.methods.base import frozen_policy_copy

__all__ = ["CRAFT", "ResidualTable", "score_function_objective"]


def score_function_objective(logp: th.Tensor, advantages: th.Tensor, mask: th.Tensor) -> th.Tensor:
    """REINFORCE over candidates (to maximise): mean over candidates of
    ``A_j * mean_t log pi(a_jt)``. logp, mask: (K, T); advantages: (K,)."""
    m = mask.float()
    per = (logp * m).sum(1) / m.sum(1).clamp(min=1.0)
    has = m.sum(1) > 0
    return (advantages * per)[has].mean() if bool(has.any()) else per.sum() * 0.0


class ResidualTable:
    """Running mean of ``R_closed - R_proxy`` per proxy outcome code (0..4), EMA with
    ``decay`` after the first sample of an outcome; 0 for outcomes not seen yet."""

    def __init__(self, decay: float) -> None:
        self.decay = float(decay)
        self.value = np.zeros(5, np.float64)
        self.count = np.zeros(5, np.int64)

    def update(self, outcome: int, residual: float) -> None:
        o = int(outcome)
        self.value[o] = residual if self.count[o] == 0 else self.decay * self.value[o] + (1 - self.decay) * residual
        self.count[o] += 1

    def correct(self, returns: np.ndarray, outcomes: np.ndarray) -> np.ndarray:
        """Proxy returns (n,) plus the residual of each one's outcome (n,)."""
        return np.asarray(returns, np.float64) + self.value[np.asarray(outcomes, np.int64)]

    def as_dict(self) -> dict[str, list]:
        return {"value": self.value.tolist(), "count": self.count.tolist()}


class CRAFT(ContinuationPPO):
    """CRAFT-dagger (see the module docstring).

    Args:
        proxy_hold: decisions a co-player's last action is held (5, 0.5 s).
        proxy_decay: per-decision factor of its controls afterwards, in [0, 1) (0.8).
        residual_rollouts: closed-loop continuations per group, in [1, group_size / 2] (1).
        residual_decay: EMA factor of the residual table, in [0, 1) (0.9).
        ema_decay: EMA factor of the policy per update, in [0, 1) (0.95).
        kl_forward_coef: weight of KL(pi_EMA || pi) (0.1).
        kl_reverse_coef: weight of KL(pi || pi_EMA) (0.01).
        Other arguments: :class:`cpalgo.baselines.continuations.ContinuationPPO`'s and PPO's.

    Call :meth:`on_anchor_loaded` after loading the anchor (the registry does) to start the
    EMA there; otherwise (and after ``load``: the EMA copy is not saved) it starts from the
    weights present at the first group update.

    Attributes:
        ema_policy: the EMA copy (frozen, updated after every update).
        residual: the :class:`ResidualTable` (saved with the model).
    """

    _RUNTIME_ATTRS: ClassVar[tuple[str, ...]] = ContinuationPPO._RUNTIME_ATTRS + ("_ema_logits", "ema_policy")

    def __init__(self, policy: Any, env: Any, proxy_hold: int = 5, proxy_decay: float = 0.8,
                 residual_rollouts: int = 1, residual_decay: float = 0.9, ema_decay: float = 0.95,
                 kl_forward_coef: float = 0.1, kl_reverse_coef: float = 0.01, **kwargs: Any) -> None:
        self.proxy_hold = proxy_hold
        self.proxy_decay = proxy_decay
        self.residual_rollouts = residual_rollouts
        self.residual_decay = residual_decay
        self.ema_decay = ema_decay
        self.kl_forward_coef = kl_forward_coef
        self.kl_reverse_coef = kl_reverse_coef
        self.ema_policy: Any = None
        self.residual: ResidualTable | None = None
        super().__init__(policy, env, **kwargs)

    def _validate_settings(self) -> None:
        super()._validate_settings()
        check_number("proxy_hold", self.proxy_hold, low=0, integer=True)
        check_number("proxy_decay", self.proxy_decay, low=0.0, high=1.0, high_open=True)
        check_number("residual_rollouts", self.residual_rollouts, low=1, high=int(self.group_size) // 2, integer=True)
        check_number("residual_decay", self.residual_decay, low=0.0, high=1.0, high_open=True)
        check_number("ema_decay", self.ema_decay, low=0.0, high=1.0, high_open=True)
        check_number("kl_forward_coef", self.kl_forward_coef, low=0.0)
        check_number("kl_reverse_coef", self.kl_reverse_coef, low=0.0)

    def _reset_runtime(self) -> None:
        super()._reset_runtime()
        self._ema_logits: th.Tensor | None = None

    def _setup_model(self) -> None:
        super()._setup_model()
        if self.residual is None:
            self.residual = ResidualTable(float(self.residual_decay))

    def on_anchor_loaded(self) -> None:
        """Start the EMA at the current (the anchor's) weights."""
        self.ema_policy = frozen_policy_copy(self)

    # ------------------------------------------------------------------ groups
    def _proxy_fn(self) -> ProxyFn:
        hold, decay, dynamics = int(self.proxy_hold), float(self.proxy_decay), self.dynamics
        return lambda last, k: hold_then_decay(last, k, hold, decay, dynamics)

    def _group_jobs(self, roots: list[ContinuationRoot]) -> list[GroupJob]:
        g, r = int(self.group_size), int(self.residual_rollouts)
        traffic = ["policy"] * r + ["proxy"] * (g - r)
        draw = np.arange(g)
        draw[r:2 * r] = np.arange(r)  # closed-loop i and proxy r + i share the focal draws
        return [GroupJob(root=root, traffic=traffic, draw_ids=draw.copy()) for root in roots]

    def corrected_returns(self, result: GroupResult) -> np.ndarray:
        """(G,) returns with the proxy candidates corrected by the residual table (after
        updating the table with this group's closed-loop / proxy pairs)."""
        assert self.residual is not None
        r = int(self.residual_rollouts)
        for i in range(r):
            self.residual.update(result.outcome[r + i], float(result.returns[i] - result.returns[r + i]))
        out = np.asarray(result.returns, np.float64).copy()
        out[r:] = self.residual.correct(result.returns[r:], result.outcome[r:])
        return out

    def _use_groups(self, roots: list[ContinuationRoot], results: list[GroupResult]) -> None:
        corrected = np.stack([self.corrected_returns(res) for res in results])
        advantages = group_normalized(corrected)
        self._group_batch = collate_continuations(roots, results, list(advantages), device=self.device)
        if self.ema_policy is None:
            self.on_anchor_loaded()
        self._ema_logits = None
        if self._group_batch is not None:
            with th.no_grad():
                self._ema_logits = continuation_logits(self.ema_policy, self._group_batch)
        for o, name in enumerate(("running", "goal", "collision", "offroad", "timeout")):
            if self.residual.count[o]:
                self.logger.record(f"craft/residual_{name}", float(self.residual.value[o]))

    def _generation_terms(self, clip_range: float) -> dict[str, th.Tensor]:
        batch = self._group_batch
        assert batch is not None and self._ema_logits is not None
        logits = continuation_logits(self.policy, batch)
        logp = th.log_softmax(logits, -1).gather(-1, batch.actions[..., None]).squeeze(-1)
        score = score_function_objective(logp, batch.advantages, batch.mask)
        forward = masked_mean(categorical_kl(self._ema_logits, logits), batch.mask)
        reverse = masked_mean(categorical_kl(logits, self._ema_logits), batch.mask)
        return {"craft_score_loss": -float(self.group_coef) * score,
                "craft_kl_forward": float(self.kl_forward_coef) * forward,
                "craft_kl_reverse": float(self.kl_reverse_coef) * reverse}

    # ------------------------------------------------------------------ EMA
    @th.no_grad()
    def update_ema(self) -> None:
        """``ema <- decay * ema + (1 - decay) * policy`` for every parameter and buffer."""
        if self.ema_policy is None:
            self.on_anchor_loaded()
            return
        d = float(self.ema_decay)
        ema_state = self.ema_policy.state_dict()
        for name, value in self.policy.state_dict().items():
            if value.dtype.is_floating_point:
                ema_state[name].mul_(d).add_(value.to(ema_state[name].device), alpha=1.0 - d)
            else:
                ema_state[name].copy_(value)

    def _after_train(self) -> None:
        self._ema_logits = None
        self.update_ema()
        super()._after_train()
