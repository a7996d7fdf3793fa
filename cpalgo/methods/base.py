"""Shared pieces of the post-training methods: equal-budget ``learn`` and frozen copies.

Every method of :mod:`cpalgo.methods` is a subclass of :class:`cpalgo.CounterPlay` (which
is sb3-contrib's ``RecurrentPPO`` with hooks) and inherits :class:`EqualBudgetMixin`, so
``model.learn(B)`` means the same thing for all of them: train until ``B_post``, the
number of live agent transitions the method simulated (main rollout, branches, rewinds,
opponents, all counted in ``model.budget``), reaches ``B``: the last rollout stops at the
step that reaches it (``CounterPlay.collect_rollouts``), so every method ends within one
step of live agents of ``B``.
"""

from __future__ import annotations

from typing import Any

import torch as th
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy

from cpalgo.counterplay.algorithm import CounterPlay

__all__ = ["EqualBudgetMixin", "BudgetedCounterPlay", "frozen_policy_copy", "base_vec_env"]


class EqualBudgetMixin:
    """``learn(B)``: train until ``model.budget.total >= B`` (B_post, live agent transitions).

    * ``post_budget`` is set to ``budget.total + B``, so the budget decides when training
      stops (no generation starts once it is reached) even where a method's SB3 step
      counter would disagree; CounterPlay's ``num_timesteps`` counts B_post too.
    * SB3's ``progress_remaining`` (learning-rate and clip-range schedules, e.g. the
      post-training ``cosine(3e-5)``) is ``1 - B_post / B``, so every method anneals over
      the same budget.
    * ``learn(B, reset_num_timesteps=False)`` continues a run whose budget totals were
      restored (grid resume): training stops at the same ``B``.
    """

    budget: Any
    post_budget: int | None

    def learn(self, total_timesteps: int, callback: Any = None, log_interval: int = 1, tb_log_name: str = "run",
              reset_num_timesteps: bool = True, progress_bar: bool = False) -> Any:
        """Train ``total_timesteps`` more B_post transitions: until ``budget.total`` reaches
        its value at this call plus ``total_timesteps`` (SB3's meaning of the argument)."""
        more = int(total_timesteps)
        if more <= 0:
            raise ValueError(f"total_timesteps: the post-training budget B_post must be > 0, got {total_timesteps!r}")
        limit = int(self.budget.total) + more
        self.post_budget = limit
        self.budget.post_budget = limit
        return super().learn(more, callback=callback, log_interval=log_interval,  # type: ignore[misc]
                             tb_log_name=tb_log_name, reset_num_timesteps=reset_num_timesteps,
                             progress_bar=progress_bar)

    def _update_current_progress_remaining(self, num_timesteps: int, total_timesteps: int) -> None:
        limit = self.budget.post_budget
        if limit:
            self._current_progress_remaining = max(0.0, 1.0 - float(self.budget.total) / float(limit))
        else:  # no budget set: SB3's own definition
            super()._update_current_progress_remaining(num_timesteps, total_timesteps)  # type: ignore[misc]


class BudgetedCounterPlay(EqualBudgetMixin, CounterPlay):
    """:class:`cpalgo.CounterPlay` with the equal-budget ``learn``: CounterPlay itself, its
    ablations and (``counterfactual=False``) PPO-Continue."""


def frozen_policy_copy(model: Any) -> RecurrentActorCriticPolicy:
    """A frozen copy of ``model.policy`` (same class and network, eval mode, no gradients,
    no optimiser state copied): the anchor teacher or an opponent checkpoint."""
    policy = model.policy
    clone = model.policy_class(model.observation_space, model.action_space, model.lr_schedule,
                               use_sde=model.use_sde, **model.policy_kwargs)
    clone.load_state_dict(policy.state_dict())
    clone = clone.to(model.device)
    clone.set_training_mode(False)
    for p in clone.parameters():
        p.requires_grad_(False)
    return clone


def base_vec_env(env: Any) -> Any:
    """The innermost VecEnv under SB3 wrappers (``VecMonitor`` & co. keep it in ``.venv``)."""
    while hasattr(env, "venv"):
        env = env.venv
    return env


def policy_parameters_equal(a: th.nn.Module, b: th.nn.Module) -> bool:
    """Whether two policies hold identical parameters (tests and sanity checks)."""
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(th.equal(sa[k], sb[k]) for k in sa)
