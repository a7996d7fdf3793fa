"""Distillation controls of the seed paper's Table IV: imitate a frozen anchor's driving
style directly, without backtracking, search or verification.

:class:`StyleDistillation` is PPO on the main self-play rollout (PPO-Continue) plus
CounterPlay's distillation term, with teachers taken from the main rollout instead of from
verified retries:

* a *teacher* is one live agent's stretch of the rollout (from its first step in the
  rollout, or its episode start, to its episode end or the rollout's end); at most
  ``distill_segments`` of them are drawn uniformly per generation (CounterPlay finds about
  70 verified retries per generation in the paper);
* the teacher probabilities are the **frozen anchor's** on those observations with the
  condition's style fields replaced by ``teacher_style`` (``aggressive`` or ``cautious``)
  and the agent's own task fields kept;
* the student is the policy under training on the same observations under the deployment
  condition (``deploy_condition``, normal): style fields of w_dep, the agent's task fields
  (:func:`cpalgo.counterplay.distill.collate_teachers`);
* the loss is CounterPlay's: ``distill_coef`` (0.5) x KL(teacher || student), averaged per
  teacher then over teachers, in ``distill_minibatches`` (4) PPO minibatch updates per
  generation. The budget is the main rollout's live transitions (no branches).

LSTM memory: a stretch that starts at an episode start starts from zero memory for both
networks (exact). A stretch that starts mid-episode (at a rollout boundary) starts both the
anchor and the student from the memory the rollout stored there (the policy's, under the
agent's own condition): the anchor's memory under the styled view of the earlier steps is
not known without replaying the episode.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch as th

from cpalgo.common.policy_utils import actor_logits
from cpalgo.counterplay.algorithm import CounterPlay
from cpalgo.counterplay.distill import Teacher
from cpalgo.methods.base import EqualBudgetMixin, frozen_policy_copy
from cpsim.conditions import PROFILE_ALIASES, PROFILES, STYLE_MASK, TRAIN_HIGH, TRAIN_LOW

__all__ = ["StyleDistillation", "raw_conditions_from_obs", "rollout_segments"]


def raw_conditions_from_obs(obs: np.ndarray, layout: Any) -> np.ndarray:
    """Raw (..., 10) conditions read back from observations (..., D): the inverse of
    :func:`cpsim.conditions.normalize_condition` on the layout's condition slice."""
    x = np.asarray(obs, np.float32)[..., layout.condition]
    return (TRAIN_LOW + (x + 1.0) * 0.5 * (TRAIN_HIGH - TRAIN_LOW)).astype(np.float32)


def rollout_segments(active: np.ndarray, episode_starts: np.ndarray) -> list[tuple[int, int, int]]:
    """Stretches of one live agent in a rollout: ``(slot, first step, length)``.

    Args:
        active: (T, N) bool, the slot held a live learner agent at that step.
        episode_starts: (T, N) bool, an episode started at that step.
    A stretch starts at an active step whose predecessor is inactive, at an episode start,
    or at the rollout's first step, and runs while the next step continues it.
    """
    active = np.asarray(active, bool)
    starts = np.asarray(episode_starts, bool)
    cont = np.zeros_like(active)
    cont[1:] = active[1:] & active[:-1] & ~starts[1:]
    first = active & ~cont
    out: list[tuple[int, int, int]] = []
    t_max = active.shape[0]
    for t0, n in zip(*np.nonzero(first)):
        t = int(t0)
        while t + 1 < t_max and cont[t + 1, n]:
            t += 1
        out.append((int(n), int(t0), t - int(t0) + 1))
    return out


class StyleDistillation(EqualBudgetMixin, CounterPlay):
    """Distillation control (see the module docstring).

    Args:
        teacher_style: profile whose style fields the frozen anchor sees (``aggressive``
            for distill-aggressive, ``cautious`` for distill-cautious).
        distill_segments: teachers drawn from each rollout (64).
        counterfactual: must stay False. Other arguments: :class:`cpalgo.CounterPlay`'s
            (``distill`` must be ``"kl"``).

    Call :meth:`on_anchor_loaded` after loading the anchor's weights (the method registry
    does): that freezes the teacher. Otherwise the weights present at the first rollout
    become the teacher.

    Attributes:
        distill_totals: running counts ``teachers`` and ``teacher_steps``.
    """

    _RUNTIME_ATTRS: ClassVar[tuple[str, ...]] = CounterPlay._RUNTIME_ATTRS + ("_teacher_policy", "_segment_rng")

    def __init__(self, policy: Any, env: Any, teacher_style: str = "aggressive", distill_segments: int = 64,
                 counterfactual: bool = False, **kwargs: Any):
        self.teacher_style = teacher_style
        self.distill_segments = distill_segments
        self.distill_totals: dict[str, int] = {}
        self._teacher_policy: Any = None
        super().__init__(policy, env, counterfactual=counterfactual, **kwargs)

    def _validate_settings(self) -> None:
        super()._validate_settings()
        if PROFILE_ALIASES.get(self.teacher_style, self.teacher_style) not in PROFILES:
            raise ValueError(f"teacher_style: unknown profile {self.teacher_style!r}; accepted: {sorted(PROFILES)}")
        if int(self.distill_segments) < 1:
            raise ValueError(f"distill_segments: must be >= 1, got {self.distill_segments!r}")
        if self.counterfactual:
            raise ValueError("counterfactual: a distillation control has no search; it must be False")
        if self.distill != "kl":
            raise ValueError(f"distill: a distillation control imitates probabilities (kl), got {self.distill!r}")
        if not self.mask_inactive:
            raise ValueError("mask_inactive: a distillation control reads live slots from the masked buffer")

    def _reset_runtime(self) -> None:
        super()._reset_runtime()
        self._segment_rng = np.random.default_rng(int(self.seed or 0) + 49979687)

    def on_anchor_loaded(self) -> None:
        """Freeze the current weights (the anchor's) as the teacher."""
        self._teacher_policy = frozen_policy_copy(self)

    @property
    def teacher_policy(self) -> Any:
        """The frozen anchor whose styled probabilities are imitated."""
        return self._teacher_policy

    def _teacher_condition(self, w0: np.ndarray) -> np.ndarray:
        style = PROFILES[PROFILE_ALIASES.get(self.teacher_style, self.teacher_style)]
        return np.where(STYLE_MASK, style, w0).astype(np.float32)

    def _rollout_end(self, env: Any) -> None:
        super()._rollout_end(env)
        if self._teacher_policy is None:
            self.on_anchor_loaded()
        self._teachers = self._style_teachers()

    @th.no_grad()
    def _style_teachers(self) -> list[Teacher]:
        """Teachers of this rollout (see the module docstring)."""
        buf = self.rollout_buffer
        layout = self.env.obs_layout
        active = np.asarray(buf.active) > 0
        starts = np.asarray(buf.episode_starts) > 0
        segments = rollout_segments(active, starts)
        if not segments:
            return []
        k = min(int(self.distill_segments), len(segments))
        chosen = [segments[i] for i in np.sort(self._segment_rng.choice(len(segments), size=k, replace=False))]
        t_max = max(length for _, _, length in chosen)
        d = buf.observations.shape[-1]
        teacher_obs = np.zeros((k, t_max, d), np.float32)
        layers, _, hidden = self.policy.lstm_actor.num_layers, None, self.policy.lstm_actor.hidden_size
        mem = np.zeros((4, layers, k, hidden), np.float32)
        conditions = []
        for i, (n, t0, length) in enumerate(chosen):
            obs = np.asarray(buf.observations[t0:t0 + length, n], np.float32)
            w0 = raw_conditions_from_obs(obs[0], layout)
            conditions.append(w0)
            teacher_obs[i, :length] = layout.replace_condition(obs, self._teacher_condition(w0))
            if not starts[t0, n]:
                for j, name in enumerate(("hidden_states_pi", "cell_states_pi", "hidden_states_vf", "cell_states_vf")):
                    mem[j, :, i] = getattr(buf, name)[t0, :, n]
        device = self.device
        flat = th.as_tensor(teacher_obs.reshape(k * t_max, d), device=device)
        memory = th.as_tensor(mem, device=device)
        logits, _ = actor_logits(self._teacher_policy, flat, (memory[0].contiguous(), memory[1].contiguous()),
                                 th.zeros(k * t_max, device=device))
        logits = logits.reshape(k, t_max, -1)
        teachers = []
        for i, (n, t0, length) in enumerate(chosen):
            teachers.append(Teacher(
                obs=th.as_tensor(teacher_obs[i, :length], device=device),
                logits=logits[i, :length].clone(),
                actions=th.as_tensor(np.asarray(buf.actions[t0:t0 + length, n]).reshape(-1), device=device).long(),
                rewards=th.as_tensor(np.asarray(buf.rewards[t0:t0 + length, n]).reshape(-1), device=device).float(),
                pi_state=(memory[0, :, i].clone(), memory[1, :, i].clone()),
                vf_state=(memory[2, :, i].clone(), memory[3, :, i].clone()),
                condition=conditions[i],
                profile=str(self.teacher_style),
                root_step=int(t0),
                failure_step=int(t0 + length - 1),
            ))
        self.distill_totals["teachers"] = self.distill_totals.get("teachers", 0) + len(teachers)
        self.distill_totals["teacher_steps"] = self.distill_totals.get("teacher_steps", 0) + sum(c[2] for c in chosen)
        return teachers
