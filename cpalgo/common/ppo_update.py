"""The PPO update of every cpalgo algorithm: sb3-contrib 2.9.2's ``RecurrentPPO.train`` with hooks.

One copy of the loop serves :meth:`cpalgo.counterplay.algorithm.CounterPlay.train` (and so
every method built on CounterPlay) and :meth:`cpalgo.common.hooked_train.HookedPPO.train`
(the adapted post-training baselines). It runs the parent's operations in the parent's
order, so with ``masked=False``, no hooks and sb3-contrib's policy class the parameters
after an update are bit-identical to ``RecurrentPPO``'s (``tests/cpalgo/test_counterplay_core.py``).

An update is two calls: :func:`begin_update` (training mode, learning rate, clip ranges),
then :func:`run_update` (the epochs over the rollout buffer, then the ``train/`` logs). What
a caller can add to the parent's loop:

* ``masked``: minibatches made only of inactive slots are skipped, and the explained
  variance is taken over live transitions (CounterPlay's ``mask_inactive``; the losses are
  masked by the buffer's ``mask`` either way).
* ``clip_bounds``: ``(low, high)``, the ratio is clipped to ``[1 - low, 1 + high]`` (DAPO's
  decoupled clip); default ``clip_range`` on both sides.
* ``minibatch_terms``: extra loss terms of every minibatch, given the minibatch, its live
  mask and the current policy's logits on it (SPICED's KL to its reference); logged as
  they are computed, like the PPO losses.
* ``scheduled``: :class:`ScheduledTerms`, loss terms that join a few minibatch updates
  spread over all the epochs (CounterPlay's distillation, the continuation baselines'
  group objectives); the updates that could not carry them (early stop, skipped
  minibatches) run on their own after the loop; logged per update that applied them.

Data-parallel (a ``torch.distributed`` process group of more than one rank is initialised,
:mod:`cpalgo.common.distributed`): every rank holds its own rollout and the ranks take the
same optimizer steps. Each step's gradient is averaged over the ranks that had data for it
before the norm clip; an epoch runs the largest minibatch count of any rank, a rank whose
minibatches ran out (or whose minibatch holds no live transition) adds a zero gradient to
the others' steps; early stopping compares the ranks' mean KL with ``target_kl``; the
scheduled updates owed after the loop are the largest count of any rank. The ``train/``
logs stay each rank's own. Without a process group none of this runs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.utils import explained_variance

from cpalgo.common.distributed import agree_max, average_gradients, data_parallel, joint_mean
from cpalgo.policies import sequence_lengths

__all__ = ["ScheduledTerms", "UpdateLog", "begin_update", "run_update", "normalize_advantages", "spread_schedule"]

#: ``(rollout_data, mask, logits) -> {name: scalar term}``: see :func:`run_update`.
MinibatchTerms = Callable[[Any, th.Tensor, th.Tensor], dict[str, th.Tensor]]


def spread_schedule(k: int, total_updates: int) -> set[int]:
    """Indices (0 .. total_updates - 1) of ``min(k, total_updates)`` minibatch updates spread
    evenly over an update's ``total_updates`` minibatches (first and last included)."""
    if total_updates <= 0:
        return set()
    return set(np.linspace(0, total_updates - 1, min(int(k), total_updates)).round().astype(int).tolist())


@dataclass
class ScheduledTerms:
    """Loss terms added to ``minibatches`` of one update's minibatch updates.

    Attributes:
        compute: ``() -> {name: scalar tensor with grad}``, called once per update that
            carries the terms.
        minibatches: how many minibatch updates carry them (:func:`spread_schedule` over
            ``n_epochs`` x the buffer's minibatches per pass).
        weight: the loss adds ``weight * term`` (the log keeps the unweighted term); None:
            the term enters the loss as it is.
        owed_without_minibatches: updates owed when the rollout yields no minibatch at all
            (they run on their own).
        logs: name -> the term's value at every update that applied it (filled by
            :func:`run_update`).
    """

    compute: Callable[[], dict[str, th.Tensor]]
    minibatches: int
    weight: float | None = None
    owed_without_minibatches: int = 0
    logs: dict[str, list[float]] = field(default_factory=dict)
    at: set[int] = field(default_factory=set, init=False)
    pending: int = field(default=0, init=False)

    def schedule(self, total_updates: int) -> None:
        """Choose the carrying updates among ``total_updates`` minibatch updates."""
        self.at = spread_schedule(self.minibatches, total_updates)
        self.pending = len(self.at) if self.at else int(self.owed_without_minibatches)

    def weighted(self, terms: dict[str, th.Tensor]) -> list[th.Tensor]:
        """The terms as they enter the loss."""
        if self.weight is None:
            return list(terms.values())
        return [self.weight * term for term in terms.values()]

    def record(self, terms: dict[str, th.Tensor]) -> None:
        """Log the terms of one update that applied them."""
        for name, term in terms.items():
            self.logs.setdefault(name, []).append(term.item())


@dataclass
class UpdateLog:
    """What one update measured (lists over its minibatch updates, the parent's logs).

    ``approx_kl_divs`` holds the last epoch's only (the parent's ``train/approx_kl``);
    ``term_logs`` the minibatch terms by name; ``loss`` the last minibatch's total loss.
    """

    entropy_losses: list[float] = field(default_factory=list)
    pg_losses: list[float] = field(default_factory=list)
    value_losses: list[float] = field(default_factory=list)
    clip_fractions: list[float] = field(default_factory=list)
    approx_kl_divs: list[np.ndarray] = field(default_factory=list)
    term_logs: dict[str, list[float]] = field(default_factory=dict)
    loss: th.Tensor | None = None


def begin_update(model: Any) -> tuple[float, float | None]:
    """The parent's preamble: training mode, learning rate; returns ``(clip_range,
    clip_range_vf)`` at the current progress (``clip_range_vf`` None when unset)."""
    model.policy.set_training_mode(True)
    model._update_learning_rate(model.policy.optimizer)
    clip_range = model.clip_range(model._current_progress_remaining)
    clip_range_vf = None
    if model.clip_range_vf is not None:
        clip_range_vf = model.clip_range_vf(model._current_progress_remaining)
    return clip_range, clip_range_vf


def _optimizer_step(model: Any, loss: th.Tensor | None) -> None:
    """Backward, gradient-norm clip to ``max_grad_norm``, one optimizer step.

    Data-parallel, the gradients are averaged over the ranks (before the clip, so every rank
    clips the same gradient) and ``loss`` None is this rank's zero share of a step the others
    take; when no rank had a loss, no rank steps. Without a process group ``loss`` is a
    tensor and the step is the parent's.
    """
    model.policy.optimizer.zero_grad()
    if loss is not None:
        loss.backward()
    if data_parallel() and not average_gradients(model.policy.parameters(), contributes=loss is not None):
        return  # no rank had data for this step: every rank skips it alike
    th.nn.utils.clip_grad_norm_(model.policy.parameters(), model.max_grad_norm)
    model.policy.optimizer.step()


def _minibatches(model: Any, count: int | None) -> Any:
    """One pass of ``model.rollout_buffer.get(model.batch_size)``; with ``count`` (data-
    parallel: the ranks' agreed minibatch count) padded with None up to ``count`` items."""
    yielded = 0
    for rollout_data in model.rollout_buffer.get(model.batch_size):
        yielded += 1
        yield rollout_data
    if count is not None:
        for _ in range(count - yielded):
            yield None


def _ppo_loss(model: Any, rollout_data: Any, actions: th.Tensor, mask: th.Tensor, clip_range: float,
              clip_bounds: tuple[float, float] | None, clip_range_vf: float | None, log: UpdateLog
              ) -> tuple[th.Tensor, th.Tensor]:
    """The parent's clipped surrogate + value + entropy loss of one minibatch.

    Args:
        rollout_data: the minibatch (``n`` rows: padded sequences).
        actions: (n,) long for Discrete spaces, the stored actions otherwise.
        mask: (n,) bool, the real (and, masked, live) transitions the means run over.
    Returns:
        ``(loss, log_prob)``: the scalar loss and the (n,) log-probabilities of ``actions``
        under the current policy; the per-term values are appended to ``log``.
    """
    # the padding after each sequence's last counted step is skipped by a fused policy's LSTM
    with sequence_lengths(model.policy, mask, rollout_data.lstm_states.pi[0].shape[1]):
        values, log_prob, entropy = model.policy.evaluate_actions(
            rollout_data.observations, actions, rollout_data.lstm_states, rollout_data.episode_starts,
        )
    values = values.flatten()
    advantages = rollout_data.advantages
    if model.normalize_advantage:
        advantages = normalize_advantages(advantages, mask)

    # ratio between old and new policy, should be one at the first iteration
    ratio = th.exp(log_prob - rollout_data.old_log_prob)
    policy_loss_1 = advantages * ratio
    if clip_bounds is None:
        policy_loss_2 = advantages * th.clamp(ratio, 1 - clip_range, 1 + clip_range)
        clipped = th.abs(ratio - 1) > clip_range
    else:
        low, high = clip_bounds
        policy_loss_2 = advantages * th.clamp(ratio, 1 - low, 1 + high)
        clipped = (ratio < 1 - low) | (ratio > 1 + high)
    policy_loss = -th.mean(th.min(policy_loss_1, policy_loss_2)[mask])
    log.pg_losses.append(policy_loss.item())
    log.clip_fractions.append(th.mean(clipped.float()[mask]).item())

    if clip_range_vf is None:
        values_pred = values
    else:
        # clip the difference between old and new value (depends on the reward scaling)
        values_pred = rollout_data.old_values + th.clamp(values - rollout_data.old_values, -clip_range_vf, clip_range_vf)
    # value loss using the TD(gae_lambda) target, padded sequences masked
    value_loss = th.mean(((rollout_data.returns - values_pred) ** 2)[mask])
    log.value_losses.append(value_loss.item())

    if entropy is None:
        # approximate entropy when no analytical form
        entropy_loss = -th.mean(-log_prob[mask])
    else:
        entropy_loss = -th.mean(entropy[mask])
    log.entropy_losses.append(entropy_loss.item())

    return policy_loss + model.ent_coef * entropy_loss + model.vf_coef * value_loss, log_prob


def normalize_advantages(advantages: th.Tensor, mask: th.Tensor) -> th.Tensor:
    """Advantages centred and scaled by their mean and std over ``mask`` (both (n,)), as
    sb3-contrib does; left as they are when fewer than two transitions are masked in, where
    the std is undefined (a minibatch of one live transition made every logit NaN)."""
    live = advantages[mask]
    if live.numel() < 2:
        return advantages
    return (advantages - live.mean()) / (live.std() + 1e-8)


def run_update(model: Any, clip_range: float, clip_range_vf: float | None, *, masked: bool,
               clip_bounds: tuple[float, float] | None = None, minibatch_terms: MinibatchTerms | None = None,
               scheduled: Sequence[ScheduledTerms] = ()) -> UpdateLog:
    """``n_epochs`` passes over ``model.rollout_buffer`` (see the module docstring), then the
    remaining scheduled updates and the parent's ``train/`` logs.

    Args:
        model: the algorithm (a ``RecurrentPPO``) after :func:`begin_update`.
        clip_range, clip_range_vf: :func:`begin_update`'s.
        masked: skip all-inactive minibatches; explained variance over live transitions.
        clip_bounds: ``(low, high)`` of the ratio clip (None: ``clip_range`` both sides).
        minibatch_terms: ``(rollout_data, mask, logits) -> {name: scalar}`` added to every
            minibatch's loss; ``mask`` (n,) bool and ``logits`` (n, n_actions) with grad,
            taken right after ``evaluate_actions`` (Discrete action spaces).
        scheduled: the scheduled terms of this update (:class:`ScheduledTerms`).
    Returns:
        The :class:`UpdateLog` (already logged under ``train/``, except the extra terms).
    """
    log = UpdateLog()
    parallel = data_parallel()
    # data-parallel: every rank runs as many minibatches per epoch as the rank with the most
    # (live transitions differ between ranks), so every rank takes every optimizer step
    agreed = agree_max(model.rollout_buffer.num_minibatches(model.batch_size)) if parallel else None
    if scheduled:
        per_epoch = agreed if agreed is not None else model.rollout_buffer.num_minibatches(model.batch_size)
        total = model.n_epochs * per_epoch
        for terms in scheduled:
            terms.schedule(total)
    update = 0
    continue_training = True
    for epoch in range(model.n_epochs):
        log.approx_kl_divs = []
        for rollout_data in _minibatches(model, agreed):
            if rollout_data is None or (masked and not bool((rollout_data.mask > 1e-8).any())):
                update += 1
                if not parallel:
                    continue  # every transition of this minibatch is an inactive slot: nothing to learn
                # nothing here for this rank: the other ranks may have data, decide and step with them
                if model.target_kl is not None and joint_mean(None) > 1.5 * model.target_kl:
                    continue_training = False
                    break
                _optimizer_step(model, None)
                continue
            actions = rollout_data.actions
            if isinstance(model.action_space, spaces.Discrete):
                # convert discrete action from float to long
                actions = rollout_data.actions.long().flatten()
            mask = rollout_data.mask > 1e-8
            carried = [terms for terms in scheduled if update in terms.at and terms.pending > 0]
            update += 1

            loss, log_prob = _ppo_loss(model, rollout_data, actions, mask, clip_range, clip_bounds, clip_range_vf, log)
            extra: dict[str, th.Tensor] = {}
            if minibatch_terms is not None:
                # the shared action distribution: its logits before anything else runs the policy
                extra = minibatch_terms(rollout_data, mask, model.policy.action_dist.distribution.logits)
            carried_terms = [(terms, terms.compute()) for terms in carried]
            carried_weighted = [terms.weighted(values) for terms, values in carried_terms]
            for name, term in extra.items():
                loss = loss + term
                log.term_logs.setdefault(name, []).append(term.item())
            for weighted in carried_weighted:
                for term in weighted:
                    loss = loss + term
            log.loss = loss

            # approximate reverse KL for early stopping (sb3 issue #417, PR #419, http://joschu.net/blog/kl-approx.html)
            with th.no_grad():
                log_ratio = log_prob - rollout_data.old_log_prob
                approx_kl_div = th.mean(((th.exp(log_ratio) - 1) - log_ratio)[mask]).cpu().numpy()
                log.approx_kl_divs.append(approx_kl_div)
            # data-parallel, the ranks stop together on their mean KL (only all-reduced when used)
            stop_kl = approx_kl_div
            if parallel and model.target_kl is not None:
                stop_kl = joint_mean(float(approx_kl_div))
            if model.target_kl is not None and stop_kl > 1.5 * model.target_kl:
                continue_training = False
                if model.verbose >= 1:
                    print(f"Early stopping at step {epoch} due to reaching max kl: {stop_kl:.2f}")
                break

            _optimizer_step(model, loss)
            for terms, values in carried_terms:
                terms.record(values)
                terms.pending -= 1

        model._n_updates += 1
        if not continue_training:
            break

    for terms in scheduled:
        _run_owed(model, terms)
    _log_update(model, log, clip_range, clip_bounds, clip_range_vf, masked)
    return log


def _run_owed(model: Any, terms: ScheduledTerms) -> None:
    """The scheduled updates no minibatch carried (early stop, skipped or no minibatches),
    each an optimizer step on the terms alone. Data-parallel, every rank takes the largest
    count owed by any rank, adding a zero gradient to the steps it owes nothing for."""
    if not data_parallel():
        while terms.pending > 0:
            values = terms.compute()
            if not values:
                break
            _optimizer_step(model, sum(terms.weighted(values)))
            terms.record(values)
            terms.pending -= 1
        return
    for _ in range(agree_max(terms.pending)):
        values = terms.compute() if terms.pending > 0 else {}
        _optimizer_step(model, sum(terms.weighted(values)) if values else None)
        if values:
            terms.record(values)
            terms.pending -= 1
        else:
            terms.pending = 0  # nothing left to compute here: the rank owes no more


def _mean(values: list[Any]) -> Any:
    return np.mean(values) if values else float("nan")


def _log_update(model: Any, log: UpdateLog, clip_range: float, clip_bounds: tuple[float, float] | None,
                clip_range_vf: float | None, masked: bool) -> None:
    """The parent's ``train/`` logs (explained variance over live transitions when
    ``masked``; ``train/clip_low`` / ``clip_high`` when the clip is asymmetric)."""
    buffer_values = model.rollout_buffer.values.flatten()
    buffer_returns = model.rollout_buffer.returns.flatten()
    if masked:
        active = np.asarray(model.rollout_buffer.active).reshape(-1) > 0
        buffer_values, buffer_returns = buffer_values[active], buffer_returns[active]
    explained_var = explained_variance(buffer_values, buffer_returns) if buffer_values.size else float("nan")

    record = model.logger.record
    record("train/entropy_loss", _mean(log.entropy_losses))
    record("train/policy_gradient_loss", _mean(log.pg_losses))
    record("train/value_loss", _mean(log.value_losses))
    record("train/approx_kl", _mean(log.approx_kl_divs))
    record("train/clip_fraction", _mean(log.clip_fractions))
    if log.loss is not None:
        record("train/loss", log.loss.item())
    record("train/explained_variance", explained_var)
    if hasattr(model.policy, "log_std"):
        record("train/std", th.exp(model.policy.log_std).mean().item())
    record("train/n_updates", model._n_updates, exclude="tensorboard")
    record("train/clip_range", clip_range)
    if clip_bounds is not None and clip_bounds[0] != clip_bounds[1]:
        record("train/clip_low", clip_bounds[0])
        record("train/clip_high", clip_bounds[1])
    if clip_range_vf is not None:
        record("train/clip_range_vf", clip_range_vf)
