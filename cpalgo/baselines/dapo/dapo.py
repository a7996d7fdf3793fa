"""DAPO adapted to recurrent self-play driving (the seed paper's DAPO-dagger baseline).

The original (Yu et al., 2025) post-trains a language model with groups of sampled answers
per prompt: group-relative advantages, a *decoupled* clip range (a lower bound
``1 - clip_low`` and a separate, higher upper bound ``1 + clip_high`` so that unlikely
tokens can still gain probability), *dynamic sampling* (prompts whose answers are all
correct or all wrong carry no signal and are dropped; sampling continues until the batch
is full) and a token-level loss mean.

Adaptation (:class:`DAPO`): a prompt is an interaction state of the main self-play rollout
(the ego approaches another vehicle, :mod:`cpalgo.baselines.continuations`); its answers are
``group_size`` (1 + 5) closed-loop continuations of the focal agent to the original
deadline, co-players reacting with the policy. An answer is correct when the focal task
completes. Each continuation's advantage is its group-normalised discounted return; groups
whose continuations all complete or all fail are dropped (their transitions still count
toward ``B_post``), and groups run in waves while the generation's continuation allowance
lasts (the budget stands in for "until the batch is full"). The loss is the decoupled
clipped surrogate averaged over every decision of every kept continuation (token-level),
added with weight ``group_coef`` to ``extra_minibatches`` PPO minibatch updates; the main
rollout's PPO uses the same decoupled clip.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th

from cpalgo.baselines.continuations import (
    ContinuationPPO,
    ContinuationRoot,
    GroupResult,
    collate_continuations,
    continuation_logits,
    group_normalized,
    mixed_outcome,
)
from cpalgo.common.hooked_train import check_number

__all__ = ["DAPO", "dynamic_sampling_keep", "decoupled_clip_objective"]


def dynamic_sampling_keep(completed: np.ndarray) -> np.ndarray:
    """DAPO's dynamic sampling on completion flags.

    Args:
        completed: (n_groups, G) bool, the focal task of each continuation completed.
    Returns:
        (n_groups,) bool, True for groups with mixed outcomes (kept).
    """
    c = np.asarray(completed, bool)
    return np.array([mixed_outcome(row) for row in c], bool).reshape(c.shape[0])


def decoupled_clip_objective(logp: th.Tensor, logp_old: th.Tensor, advantages: th.Tensor, mask: th.Tensor,
                             clip_low: float, clip_high: float) -> th.Tensor:
    """DAPO's token-level clipped surrogate (to maximise).

    Args:
        logp, logp_old: (K, T) log-probabilities of the taken actions now / when sampled.
        advantages: (K,) one advantage per continuation (broadcast over its steps).
        mask: (K, T) 1 on real decisions.
        clip_low, clip_high: the ratio is clipped to ``[1 - clip_low, 1 + clip_high]``.
    Returns:
        scalar: mean over every real decision of ``min(r A, clip(r) A)``.
    """
    ratio = th.exp(logp - logp_old)
    adv = advantages[:, None]
    surrogate = th.min(ratio * adv, th.clamp(ratio, 1.0 - clip_low, 1.0 + clip_high) * adv)
    m = mask.float()
    return (surrogate * m).sum() / m.sum().clamp(min=1.0)


class DAPO(ContinuationPPO):
    """DAPO-dagger (see the module docstring).

    Args:
        clip_low: lower clip ``epsilon_low`` in (0, 1) (0.2, DAPO's).
        clip_high: upper clip ``epsilon_high`` > 0 (0.28, DAPO's).
        dynamic_sampling: drop groups whose continuations all complete or all fail (True).
        Other arguments: :class:`cpalgo.baselines.continuations.ContinuationPPO`'s (group size,
        trigger, allowance) and PPO's.

    Attributes:
        continuation_totals: also ``groups_kept`` and ``groups_dropped``.
    """

    def __init__(self, policy: Any, env: Any, clip_low: float = 0.2, clip_high: float = 0.28,
                 dynamic_sampling: bool = True, **kwargs: Any) -> None:
        self.clip_low = clip_low
        self.clip_high = clip_high
        self.dynamic_sampling = dynamic_sampling
        super().__init__(policy, env, **kwargs)

    def _validate_settings(self) -> None:
        super()._validate_settings()
        check_number("clip_low", self.clip_low, low=0.0, high=1.0, low_open=True, high_open=True)
        check_number("clip_high", self.clip_high, low=0.0, low_open=True)
        if not isinstance(self.dynamic_sampling, (bool, np.bool_)):
            raise ValueError(f"dynamic_sampling: must be True or False, got {self.dynamic_sampling!r}")

    def _clip_bounds(self, clip_range: float) -> tuple[float, float]:
        return float(self.clip_low), float(self.clip_high)

    def _use_groups(self, roots: list[ContinuationRoot], results: list[GroupResult]) -> None:
        completed = np.stack([res.completed for res in results])
        keep = dynamic_sampling_keep(completed) if self.dynamic_sampling else np.ones(len(results), bool)
        self._bump("groups_kept", int(keep.sum()))
        self._bump("groups_dropped", int((~keep).sum()))
        kept = np.flatnonzero(keep)
        advantages = [group_normalized(results[i].returns[None])[0] for i in kept]
        self._group_batch = collate_continuations([roots[i] for i in kept], [results[i] for i in kept], advantages,
                                                  device=self.device)

    def _generation_terms(self, clip_range: float) -> dict[str, th.Tensor]:
        batch = self._group_batch
        assert batch is not None
        logits = continuation_logits(self.policy, batch)
        logp = th.log_softmax(logits, -1).gather(-1, batch.actions[..., None]).squeeze(-1)
        objective = decoupled_clip_objective(logp, batch.logp_old, batch.advantages, batch.mask,
                                             float(self.clip_low), float(self.clip_high))
        return {"dapo_group_loss": -float(self.group_coef) * objective}
