"""Distillation of verified retries into the policy under its deployment condition.

A :class:`Teacher` is one verified retry of one failed task: the focal agent's
observations from the root to the end of its task (as seen in the winning branch, i.e.
with the teacher condition w* in the condition slice), the frozen policy's logits there,
the actions taken, the rewards, and the focal agent's actor / critic LSTM memory at the
root.

The student sees the *same* observations with the condition slice replaced by the
deployment condition (style fields from w_dep, task fields kept: the task's goal test does
not change) and runs its LSTM from the stored root memory.

``kl`` (default): ``KL(teacher || student)`` averaged over each retry's steps, then over
retries. ``ppo`` (ablation): the clipped PPO surrogate on the teacher's actions with
discounted-return advantages from the frozen critic, under the deployment condition.

:class:`DistillationMixin` (one of :class:`~cpalgo.counterplay.algorithm.CounterPlay`'s
bases) prepares a generation's :class:`TeacherBatch` for the update
(``_prepare_distillation``), writing ``w_dep`` into the teachers' observations as the
policy sees them (``_student_condition_writer``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import torch as th
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from stable_baselines3.common.vec_env import unwrap_vec_normalize

from cpalgo.common.policy_utils import actor_logits, critic_values
from cpsim.conditions import STYLE_MASK

__all__ = ["DISTILL_MODES", "Teacher", "TeacherBatch", "collate_teachers", "kl_loss", "ppo_loss", "distill_loss",
           "DistillationMixin"]

DISTILL_MODES: tuple[str, ...] = ("kl", "ppo")

#: obs (..., D), raw conditions (..., 10) -> obs copy with the condition slice replaced
ReplaceCondition = Callable[[th.Tensor, th.Tensor], th.Tensor]


@dataclass
class Teacher:
    """One verified retry (all tensors on CPU or the model's device).

    Attributes:
        obs: (T, D) focal observations from the root to the focal task's end (teacher view).
        logits: (T, n_actions) frozen-policy logits under w* at those steps.
        actions: (T,) int64 actions taken in the branch.
        rewards: (T,) float32 conditioned rewards of the focal agent under w*.
        pi_state: actor (h, c), each (layers, hidden), memory at the root.
        vf_state: critic (h, c), each (layers, hidden), memory at the root.
        condition: (10,) raw condition of the focal task at the root (w0).
        profile: name of the winning panel profile.
        root_step, failure_step: decisions (episode clock) of the root and the failure.
    """

    obs: th.Tensor
    logits: th.Tensor
    actions: th.Tensor
    rewards: th.Tensor
    pi_state: tuple[th.Tensor, th.Tensor]
    vf_state: tuple[th.Tensor, th.Tensor]
    condition: np.ndarray
    profile: str = ""
    root_step: int = 0
    failure_step: int = 0

    def __post_init__(self) -> None:
        t = self.obs.shape[0]
        if t == 0:
            raise ValueError("obs: a teacher needs at least one step")
        for name in ("logits", "actions", "rewards"):
            if getattr(self, name).shape[0] != t:
                raise ValueError(f"{name}: {getattr(self, name).shape[0]} steps, obs has {t}")

    @property
    def length(self) -> int:
        return int(self.obs.shape[0])


@dataclass
class TeacherBatch:
    """Teachers padded to one tensor batch (K retries, T_max steps).

    Attributes:
        student_obs: (K * T_max, D) sequence-major student observations (condition = w_dep).
        teacher_logp: (K, T_max, n_actions) teacher log-probabilities.
        actions: (K, T_max) int64.
        mask: (K, T_max) float32, 1 on real steps, 0 on padding.
        pi_state, vf_state: (h, c), each (layers, K, hidden).
        old_logp, advantages: (K, T_max), for the PPO ablation (zeros otherwise).
    """

    student_obs: th.Tensor
    teacher_logp: th.Tensor
    actions: th.Tensor
    mask: th.Tensor
    pi_state: tuple[th.Tensor, th.Tensor]
    vf_state: tuple[th.Tensor, th.Tensor]
    old_logp: th.Tensor
    advantages: th.Tensor

    @property
    def num_teachers(self) -> int:
        return int(self.mask.shape[0])


def _pad(seqs: Sequence[th.Tensor], length: int) -> th.Tensor:
    return th.nn.utils.rnn.pad_sequence(list(seqs), batch_first=True)[:, :length]


def collate_teachers(
    teachers: Sequence[Teacher],
    deploy_condition: np.ndarray,
    replace_condition: ReplaceCondition,
    style_mask: np.ndarray,
    device: th.device | str = "cpu",
    policy: RecurrentActorCriticPolicy | None = None,
    gamma: float = 0.99,
) -> TeacherBatch:
    """Pad teachers into a :class:`TeacherBatch` with the student's view of the observations.

    Args:
        teachers: K >= 1 teachers.
        deploy_condition: (10,) raw deployment condition w_dep; only its ``style_mask``
            fields are used, the task fields stay each teacher's own.
        replace_condition: ``obs_layout.replace_condition`` (raw conditions, broadcasting).
        style_mask: (10,) bool, the fields a retry may change.
        policy: when given, the PPO-ablation fields (old log-probs of the teacher actions
            under the student view and advantages from the frozen critic) are filled.
        gamma: discount of the PPO-ablation returns.
    """
    if not teachers:
        raise ValueError("teachers: need at least one teacher")
    k = len(teachers)
    t_max = max(t.length for t in teachers)
    lengths = th.tensor([t.length for t in teachers], device=device)
    mask = (th.arange(t_max, device=device)[None, :] < lengths[:, None]).float()

    w_dep = np.asarray(deploy_condition, np.float32)
    style = np.asarray(style_mask, bool)
    student_cond = np.stack([np.where(style, w_dep, np.asarray(t.condition, np.float32)) for t in teachers])
    student_cond_t = th.as_tensor(student_cond, device=device)  # (K, 10)

    obs = _pad([t.obs.to(device) for t in teachers], t_max)  # (K, T, D)
    student_obs = replace_condition(obs, student_cond_t[:, None, :].expand(k, t_max, -1))
    student_obs = th.as_tensor(student_obs, device=device, dtype=th.float32)
    student_obs = student_obs * mask[..., None]  # padding stays exactly zero
    flat_obs = student_obs.reshape(k * t_max, -1)

    logits = _pad([t.logits.to(device).float() for t in teachers], t_max)
    teacher_logp = th.log_softmax(logits, dim=-1)
    actions = _pad([t.actions.to(device).long() for t in teachers], t_max)

    def stack_state(states: list[tuple[th.Tensor, th.Tensor]]) -> tuple[th.Tensor, th.Tensor]:
        h = th.stack([s[0].to(device) for s in states], dim=1).contiguous()  # (layers, K, hidden)
        c = th.stack([s[1].to(device) for s in states], dim=1).contiguous()
        return h, c

    pi_state = stack_state([t.pi_state for t in teachers])
    vf_state = stack_state([t.vf_state for t in teachers])

    old_logp = th.zeros(k, t_max, device=device)
    advantages = th.zeros(k, t_max, device=device)
    if policy is not None:
        with th.no_grad():
            starts = th.zeros(k * t_max, device=device)
            student_logits, _ = actor_logits(policy, flat_obs, pi_state, starts)
            logp_all = th.log_softmax(student_logits, -1).reshape(k, t_max, -1)
            old_logp = logp_all.gather(-1, actions[..., None]).squeeze(-1)
            values = critic_values(policy, flat_obs, vf_state, starts).reshape(k, t_max)
            rewards = _pad([t.rewards.to(device).float() for t in teachers], t_max) * mask
            returns = th.zeros_like(rewards)
            running = th.zeros(k, device=device)
            for step in range(t_max - 1, -1, -1):  # loop over time, batched over retries
                running = rewards[:, step] + gamma * running * mask[:, step]
                returns[:, step] = running
            adv = (returns - values) * mask
            n = mask.sum()
            mean = adv.sum() / n
            std = th.sqrt((((adv - mean) * mask) ** 2).sum() / n.clamp(min=1.0))
            advantages = (adv - mean) / (std + 1e-8) * mask

    return TeacherBatch(flat_obs, teacher_logp, actions, mask, pi_state, vf_state, old_logp, advantages)


def _per_retry_mean(per_step: th.Tensor, mask: th.Tensor) -> th.Tensor:
    """Mean over each retry's real steps, then over retries. per_step, mask: (K, T)."""
    per_retry = (per_step * mask).sum(1) / mask.sum(1).clamp(min=1.0)
    return per_retry.mean()


def _student_logp(policy: RecurrentActorCriticPolicy, batch: TeacherBatch) -> th.Tensor:
    k, t_max = batch.mask.shape
    starts = th.zeros(k * t_max, device=batch.mask.device)
    logits, _ = actor_logits(policy, batch.student_obs, batch.pi_state, starts)
    return th.log_softmax(logits, dim=-1).reshape(k, t_max, -1)


def kl_loss(policy: RecurrentActorCriticPolicy, batch: TeacherBatch) -> th.Tensor:
    """Mean KL(teacher || student): per retry over its steps, then over retries (scalar)."""
    student_logp = _student_logp(policy, batch)
    teacher_p = batch.teacher_logp.exp()
    kl = (teacher_p * (batch.teacher_logp - student_logp)).sum(-1)  # (K, T)
    return _per_retry_mean(kl, batch.mask)


def ppo_loss(policy: RecurrentActorCriticPolicy, batch: TeacherBatch, clip_range: float) -> th.Tensor:
    """Clipped PPO surrogate on the teacher actions under the student view (ablation)."""
    student_logp = _student_logp(policy, batch).gather(-1, batch.actions[..., None]).squeeze(-1)
    ratio = th.exp(student_logp - batch.old_logp)
    surrogate = th.min(batch.advantages * ratio, batch.advantages * th.clamp(ratio, 1 - clip_range, 1 + clip_range))
    return -_per_retry_mean(surrogate, batch.mask)


def distill_loss(policy: RecurrentActorCriticPolicy, batch: TeacherBatch, mode: str, clip_range: float = 0.2) -> th.Tensor:
    """The distillation term for ``mode`` in :data:`DISTILL_MODES` (scalar tensor)."""
    if mode == "kl":
        return kl_loss(policy, batch)
    if mode == "ppo":
        return ppo_loss(policy, batch, clip_range)
    raise ValueError(f"distill: expected one of {DISTILL_MODES}, got {mode!r}")


class DistillationMixin:
    """A CounterPlay model's preparation of its distillation batch (see the module docstring)."""

    def _prepare_distillation(self) -> TeacherBatch | None:
        if not self._teachers or self.env is None or float(self.distill_coef) == 0.0:
            return None
        return collate_teachers(
            self._teachers, self._deploy_raw, self._student_condition_writer(), STYLE_MASK, device=self.device,
            policy=self.policy if self.distill == "ppo" else None, gamma=self.gamma,
        )

    def _student_condition_writer(self) -> Any:
        """``replace_condition(obs, raw_conditions)`` for the teachers' recorded observations.
        Those are the policy's inputs: under a ``VecNormalize`` wrapper already normalised, so
        the written condition slice gets the wrapper's normalisation too (the student then sees
        ``w_dep`` as it would in a rollout)."""
        layout = self.env.obs_layout
        vec_normalize = unwrap_vec_normalize(self.env)
        if vec_normalize is None or not vec_normalize.norm_obs:
            return layout.replace_condition
        cond = layout.condition
        mean = th.as_tensor(vec_normalize.obs_rms.mean[cond], dtype=th.float32, device=self.device)
        scale = th.as_tensor(np.sqrt(vec_normalize.obs_rms.var[cond] + vec_normalize.epsilon), dtype=th.float32,
                             device=self.device)
        clip = float(vec_normalize.clip_obs)

        def write(obs: th.Tensor, conditions: th.Tensor) -> th.Tensor:
            out = th.as_tensor(layout.replace_condition(obs, conditions), dtype=th.float32, device=self.device)
            out[..., cond] = th.clamp((out[..., cond] - mean) / scale, -clip, clip)
            return out

        return write
