"""Masked PPO with loss hooks: the training core of the adapted post-training baselines.

:class:`HookedPPO` is PPO-Continue (:class:`cpalgo.methods.base.BudgetedCounterPlay` with
``counterfactual=False``: factual self-play PPO, inactive slots masked, the equal-budget
``learn``) whose update is CounterPlay's, the one PPO update of cpalgo
(:mod:`cpalgo.common.ppo_update`, sb3-contrib 2.9.2's ``RecurrentPPO.train``), called with
hooks, so a method changes its objective without copying the loop:

* :meth:`HookedPPO._clip_bounds`: ``(low, high)`` of the ratio clip, ``ratio`` is clipped
  to ``[1 - low, 1 + high]`` (PPO: both ``clip_range``; DAPO: decoupled).
* :meth:`HookedPPO._minibatch_terms`: extra loss terms on every PPO minibatch, given the
  minibatch, its padding/activity mask and the current policy's logits there (SPICED's KL
  to its reference).
* :meth:`HookedPPO._generation_terms`: extra loss terms that do not depend on the
  minibatch (the group objectives of the continuation methods); they join
  ``extra_minibatches`` minibatch updates per generation, spread over the epochs (as
  CounterPlay's distillation term joins ``distill_minibatches``); updates that could not
  carry them (early stop, empty minibatches) run on their own after the loop.
* :meth:`HookedPPO._after_train`: after the update (EMA copies, auxiliary heads).

:class:`HookedRolloutBuffer` is the masked recurrent buffer with (a) always the active-only
minibatch path, (b) optional extra per-step fields padded into every minibatch exactly as
the observations are (``buffer.sample_extras[name]``, valid while that minibatch is being
processed), and (c) a ``before_gae`` callback that runs right before the returns and
advantages are computed (VinePPO replaces critic values there).
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from typing import Any, ClassVar

import numpy as np
import torch as th
from gymnasium import spaces

from cpalgo.common.buffers import MaskedRecurrentRolloutBuffer, padded_sequencer
from cpalgo.common.ppo_update import ScheduledTerms, begin_update, run_update
from cpalgo.counterplay.algorithm import CounterPlay
from cpalgo.methods.base import EqualBudgetMixin

__all__ = ["HookedRolloutBuffer", "HookedPPO", "masked_mean", "categorical_kl", "check_number"]


def masked_mean(x: th.Tensor, mask: th.Tensor) -> th.Tensor:
    """Mean of ``x`` over the entries where ``mask`` (same shape, bool or 0/1) is set; 0 when
    nothing is set (keeps the graph)."""
    m = mask.to(x.dtype)
    return (x * m).sum() / m.sum().clamp(min=1.0)


def categorical_kl(logits_p: th.Tensor, logits_q: th.Tensor) -> th.Tensor:
    """KL(p || q) of categorical distributions given by logits, over the last axis.

    Args:
        logits_p, logits_q: (..., n_actions) unnormalised log-probabilities.
    Returns:
        (...,) KL in nats (>= 0; exactly 0 where the two distributions are equal).
    """
    logp = th.log_softmax(logits_p.float(), dim=-1)
    logq = th.log_softmax(logits_q.float(), dim=-1)
    return (logp.exp() * (logp - logq)).sum(-1)


def check_number(name: str, value: Any, *, low: float | None = None, high: float | None = None,
                 low_open: bool = False, high_open: bool = False, integer: bool = False) -> None:
    """``ValueError`` naming ``name`` unless ``value`` is a finite number in the range
    (``low``/``high`` inclusive unless ``*_open``), and a whole number when ``integer``."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if ok:
        v = float(value)
        ok = np.isfinite(v)
        if ok and integer:
            ok = v == int(v)
        if ok and low is not None:
            ok = v > low if low_open else v >= low
        if ok and high is not None:
            ok = v < high if high_open else v <= high
    if not ok:
        lo = "" if low is None else (f"> {low}" if low_open else f">= {low}")
        hi = "" if high is None else (f"< {high}" if high_open else f"<= {high}")
        rng = " and ".join(s for s in (lo, hi) if s)
        kind = "a whole number" if integer else "a number"
        raise ValueError(f"{name}: must be {kind}{' ' + rng if rng else ''}, got {value!r}")


class HookedRolloutBuffer(MaskedRecurrentRolloutBuffer):
    """:class:`MaskedRecurrentRolloutBuffer` with extra fields and a pre-GAE callback.

    Attributes:
        extra_shapes: name -> trailing shape of an extra per-step float32 field; the field
            is ``buffer.extras[name]`` of shape (n_steps, n_envs, *shape), zero after
            ``reset``; writers fill row ``buffer.pos`` before the ``add`` of that step.
        sample_extras: name -> (n_padded, *shape) tensor of the minibatch last yielded by
            :meth:`get`, padded like its observations.
        before_gae: called with no argument at the start of
            :meth:`compute_returns_and_advantage` (values may be edited there).
    """

    extra_shapes: dict[str, tuple[int, ...]]
    extras: dict[str, np.ndarray]
    sample_extras: dict[str, th.Tensor]
    before_gae: Callable[[], None] | None

    def __init__(self, *args: Any, extra_shapes: dict[str, tuple[int, ...]] | None = None, **kwargs: Any) -> None:
        self.extra_shapes = dict(extra_shapes or {})
        self.before_gae = None
        self.sample_extras = {}
        super().__init__(*args, **kwargs)

    def reset(self) -> None:
        super().reset()
        self.extras = {name: np.zeros((self.buffer_size, self.n_envs, *shape), np.float32)
                       for name, shape in self.extra_shapes.items()}
        self.sample_extras = {}

    def compute_returns_and_advantage(self, last_values: th.Tensor, dones: np.ndarray) -> None:
        if self.before_gae is not None:
            self.before_gae()
        super().compute_returns_and_advantage(last_values, dones)

    def _uses_active_path(self) -> bool:
        # always the active path (when masking): its sequencer is the one the extras follow
        return bool(self.active_only)

    def _flatten_fields(self) -> None:
        if not self.generator_ready:
            for name in list(self.extras):
                self.extras[name] = self.swap_and_flatten(self.extras[name])
        super()._flatten_fields()

    def get(self, batch_size: int | None = None) -> Generator[Any, None, None]:
        if not self.active_only and self.extras:
            raise ValueError("active_only: extra fields need the active-only minibatch path (mask_inactive=True)")
        yield from super().get(batch_size)

    def _active_samples(self, batch_inds: np.ndarray, seq_start: np.ndarray) -> Any:
        samples = super()._active_samples(batch_inds, seq_start)
        if self.extras:
            starts, max_len, pad = padded_sequencer(seq_start, self.device)
            padded = starts.size * max_len
            self.sample_extras = {name: pad(value[batch_inds]).reshape((padded, *value.shape[1:]))
                                  for name, value in self.extras.items()}
        return samples


class HookedPPO(EqualBudgetMixin, CounterPlay):
    """PPO-Continue with loss hooks (see the module docstring).

    Args:
        extra_minibatches: minibatch updates per generation that carry
            :meth:`_generation_terms` (4, CounterPlay's ``distill_minibatches``).
        counterfactual: must stay False (no CounterPlay search).
        Every other argument is :class:`cpalgo.CounterPlay`'s; ``mask_inactive`` must stay
        True (the hooks read live slots from the masked buffer).

    Subclasses set :attr:`extra_fields` (name -> trailing shape) to get per-step buffer
    fields, and override the hooks.
    """

    #: extra per-step rollout fields (name -> trailing shape), see HookedRolloutBuffer
    extra_fields: ClassVar[dict[str, tuple[int, ...]]] = {}

    def __init__(self, policy: Any, env: Any, extra_minibatches: int = 4, counterfactual: bool = False,
                 **kwargs: Any) -> None:
        self.extra_minibatches = extra_minibatches
        super().__init__(policy, env, counterfactual=counterfactual, **kwargs)

    # ------------------------------------------------------------------ settings
    def _validate_settings(self) -> None:
        super()._validate_settings()
        check_number("extra_minibatches", self.extra_minibatches, low=1, integer=True)
        if self.counterfactual:
            raise ValueError(f"counterfactual: {type(self).__name__} runs no CounterPlay search; it must be False")
        if not self.mask_inactive:
            raise ValueError(f"mask_inactive: {type(self).__name__} reads live slots from the masked buffer; "
                             "it must be True")

    def _setup_model(self) -> None:
        super()._setup_model()
        if isinstance(self.observation_space, spaces.Dict):
            raise ValueError(f"env: {type(self).__name__} supports Box observations only")
        if not isinstance(self.action_space, spaces.Discrete):
            raise ValueError(f"env: {type(self).__name__} needs a Discrete action space, got {self.action_space}")
        old = self.rollout_buffer
        self.rollout_buffer = HookedRolloutBuffer(
            self.n_steps, self.observation_space, self.action_space, old.hidden_state_shape, self.device,
            gamma=self.gamma, gae_lambda=self.gae_lambda, n_envs=self.n_envs,
            extra_shapes=self._extra_shapes(),
        )
        self.rollout_buffer.active_only = self.mask_inactive
        self.rollout_buffer.before_gae = self._before_gae

    def _extra_shapes(self) -> dict[str, tuple[int, ...]]:
        """Extra per-step buffer fields (default: :attr:`extra_fields`)."""
        return dict(self.extra_fields)

    # ------------------------------------------------------------------ hooks
    def _before_gae(self) -> None:
        """Called right before the rollout's returns and advantages are computed."""

    def _clip_bounds(self, clip_range: float) -> tuple[float, float]:
        """``(low, high)``: the ratio is clipped to ``[1 - low, 1 + high]``."""
        return float(clip_range), float(clip_range)

    def _minibatch_terms(self, rollout_data: Any, mask: th.Tensor, logits: th.Tensor) -> dict[str, th.Tensor]:
        """Extra weighted loss terms of one PPO minibatch (name -> scalar tensor).

        Args:
            rollout_data: the minibatch (padded sequences, ``n`` rows).
            mask: (n,) bool, real live transitions.
            logits: (n, n_actions) the current policy's logits on the minibatch (with grad).
        """
        return {}

    def _has_generation_terms(self) -> bool:
        """Whether :meth:`_generation_terms` has anything to add in this update."""
        return False

    def _generation_terms(self, clip_range: float) -> dict[str, th.Tensor]:
        """Extra weighted loss terms independent of the minibatch (name -> scalar tensor)."""
        return {}

    def _after_train(self) -> None:
        """Called at the end of :meth:`train`."""

    # ------------------------------------------------------------------ train
    def train(self) -> None:
        """The shared masked PPO update (:func:`cpalgo.common.ppo_update.run_update`, CounterPlay's)
        with the hooks above; every extra term is logged as ``train/<name>`` (its mean)."""
        clip_range, clip_range_vf = begin_update(self)
        generation: list[ScheduledTerms] = []
        if self._has_generation_terms():
            # no minibatch at all: the terms still get their updates, on their own
            generation = [ScheduledTerms(compute=lambda: self._generation_terms(clip_range),
                                         minibatches=int(self.extra_minibatches),
                                         owed_without_minibatches=int(self.extra_minibatches))]
        log = run_update(self, clip_range, clip_range_vf, masked=self.mask_inactive,
                         clip_bounds=self._clip_bounds(clip_range), minibatch_terms=self._minibatch_terms,
                         scheduled=generation)
        extra_logs = dict(log.term_logs)
        for terms in generation:
            for name, values in terms.logs.items():
                extra_logs.setdefault(name, []).extend(values)
        for name, values in extra_logs.items():
            self.logger.record(f"train/{name}", float(np.mean(values)))
        self._after_train()
