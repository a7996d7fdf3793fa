"""Teacher-regularised self-play PPO: the anchor's PPO stage that keeps the teacher's styles.

Plain PPO from the imitation warm start improves completion but erases the style separation
the reactive teacher gave (``zoo/anchor.json``: 600k transitions move self-play goals from
20.6 / 34.6 / 65.4 % to 63.8 / 70.4 / 67.9 %, cautious / normal / aggressive). The reward
terms that differ between styles are small next to the goal reward, so PPO pulls every
condition towards one behaviour. :class:`TeacherPPO` adds the teacher's actions as an
auxiliary imitation term (PPO with a behaviour-cloning loss, as in DAPG or the BC term of
HR-PPO / SPICED), so the policy keeps the teacher's style-conditioned behaviour where PPO
has no reason to move and improves where the reward says so:

* during the rollout, the teacher (:func:`cpsim.expert.make_expert`, a state-based rule
  that reads every agent's condition) labels every live decision of the main rollout; the
  label is stored in the rollout buffer (``teacher_action``);
* every PPO minibatch adds ``coef`` x the masked mean negative log-likelihood of the
  teacher's action under the current policy; ``coef`` goes linearly from ``teacher_coef``
  to ``teacher_coef_final`` over the run (SB3's ``progress_remaining``).

The rest is masked self-play PPO (:class:`cpalgo.common.hooked_train.HookedPPO`: live slots
only, the fused LSTM policy, ``learn(B)`` stops at B live agent transitions). The policy is
an ordinary recurrent actor-critic, so :func:`export_recurrent_ppo` hands it to plain
sb3-contrib ``RecurrentPPO`` for shipping.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch as th
from sb3_contrib.common.recurrent.type_aliases import RNNStates

from cpalgo.common.hooked_train import HookedPPO, check_number, masked_mean
from cpalgo.methods.base import base_vec_env

__all__ = ["TeacherPPO", "export_recurrent_ppo"]


class TeacherPPO(HookedPPO):
    """Self-play PPO with the teacher's actions as an auxiliary imitation term (module docstring).

    Args:
        teacher: ``reactive`` (:class:`cpsim.expert.ReactiveExpert`, default) or ``tracking``.
        teacher_coef: weight of the imitation term at the start (1.0).
        teacher_coef_final: its weight at the end of ``learn`` (None: ``teacher_coef``).
        Other arguments: :class:`cpalgo.common.hooked_train.HookedPPO`'s and PPO's.
    """

    _RUNTIME_ATTRS: ClassVar[tuple[str, ...]] = HookedPPO._RUNTIME_ATTRS + ("_teacher", "_nll_raw", "_agree_raw")

    def __init__(self, policy: Any, env: Any, teacher: str = "reactive", teacher_coef: float = 1.0,
                 teacher_coef_final: float | None = None, **kwargs: Any) -> None:
        self.teacher = teacher
        self.teacher_coef = teacher_coef
        self.teacher_coef_final = teacher_coef_final
        super().__init__(policy, env, **kwargs)

    def _validate_settings(self) -> None:
        super()._validate_settings()
        from cpsim.expert import EXPERTS

        if self.teacher not in EXPERTS:
            raise ValueError(f"teacher: unknown teacher {self.teacher!r}; accepted: {list(EXPERTS)}")
        check_number("teacher_coef", self.teacher_coef, low=0.0)
        if self.teacher_coef_final is not None:
            check_number("teacher_coef_final", self.teacher_coef_final, low=0.0)

    def _extra_shapes(self) -> dict[str, tuple[int, ...]]:
        return {"teacher_action": ()}

    def _reset_runtime(self) -> None:
        super()._reset_runtime()
        self._teacher: Any = None
        self._nll_raw: list[float] = []
        self._agree_raw: list[float] = []

    def current_teacher_coef(self) -> float:
        """The imitation weight now: linear from ``teacher_coef`` to ``teacher_coef_final``."""
        final = self.teacher_coef if self.teacher_coef_final is None else self.teacher_coef_final
        done = 1.0 - float(self._current_progress_remaining)
        return float(self.teacher_coef) + (float(final) - float(self.teacher_coef)) * min(max(done, 0.0), 1.0)

    # ------------------------------------------------------------------ rollout
    def _teacher_for(self, sim: Any) -> Any:
        if self._teacher is None or self._teacher.sim is not sim:
            from cpsim.expert import make_expert

            self._teacher = make_expert(self.teacher, sim)
        return self._teacher

    def _policy_step(self, env: Any, obs_tensor: th.Tensor, lstm_states: RNNStates, episode_starts: th.Tensor
                     ) -> tuple[th.Tensor, th.Tensor, th.Tensor, RNNStates]:
        out = super()._policy_step(env, obs_tensor, lstm_states, episode_starts)
        sim = base_vec_env(self.env).sim
        labels = self._teacher_for(sim).actions().reshape(-1)  # (W * A,), slot order = env order
        n = obs_tensor.shape[0]
        if labels.numel() != n:
            raise ValueError(f"env: the teacher labels {labels.numel()} slots but the rollout has {n}")
        idx = self._active_index(n)
        rows = np.arange(n) if idx is None else idx.cpu().numpy()
        self.rollout_buffer.extras["teacher_action"][self.rollout_buffer.pos, rows] = \
            labels.cpu().numpy()[rows].astype(np.float32)
        return out

    # ------------------------------------------------------------------ loss
    def _minibatch_terms(self, rollout_data: Any, mask: th.Tensor, logits: th.Tensor) -> dict[str, th.Tensor]:
        target = self.rollout_buffer.sample_extras["teacher_action"].reshape(-1).long()  # (n,)
        logp = th.log_softmax(logits.float(), dim=-1)
        nll = -logp.gather(-1, target[:, None]).squeeze(-1)
        value = masked_mean(nll, mask)
        with th.no_grad():
            self._nll_raw.append(float(value.item()))
            self._agree_raw.append(float(masked_mean((logits.argmax(-1) == target).float(), mask).item()))
        return {"teacher_nll_loss": self.current_teacher_coef() * value}

    def _after_train(self) -> None:
        if self._nll_raw:
            self.logger.record("train/teacher_nll", float(np.mean(self._nll_raw)))
            self.logger.record("train/teacher_agreement", float(np.mean(self._agree_raw)))
            self.logger.record("train/teacher_coef", self.current_teacher_coef())
        self._nll_raw, self._agree_raw = [], []
        super()._after_train()


def export_recurrent_ppo(model: Any, recipe_policy: str, env: Any, **algo_kwargs: Any) -> Any:
    """A plain sb3-contrib ``RecurrentPPO`` holding ``model``'s policy weights (same network),
    so that the shipped anchor loads without cpalgo's training classes.

    Args:
        model: a trained :class:`TeacherPPO` (or any recurrent actor-critic model).
        recipe_policy: the recipe's policy name (``MlpLstmPolicy``).
        env: the env the new model is built on (the same spaces).
        algo_kwargs: the recipe's algorithm arguments (``policy_kwargs`` included).
    """
    from sb3_contrib import RecurrentPPO

    out = RecurrentPPO(recipe_policy, env, **algo_kwargs)
    out.policy.load_state_dict(model.policy.state_dict(), strict=True)
    # same parameters in the same order, so Adam's moments carry over and a continued run resumes them
    out.policy.optimizer.load_state_dict(model.policy.optimizer.state_dict())
    out.num_timesteps = int(model.num_timesteps)
    return out
