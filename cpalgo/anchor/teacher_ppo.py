"""Teacher-regularised self-play PPO: the anchor's PPO stage that keeps the teacher's styles.

Plain PPO from the imitation warm start improves completion but erases the style separation
the reactive teacher gave (``zoo/anchor_imitation.json``: 600k transitions move self-play goals from
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
* with ``style_pairs`` K > 0 (paired style labels, as :class:`cpalgo.anchor.imitation.ImitationConfig`'s
  during imitation), every live decision is also labelled under K swapped conditions: each
  slot's style fields replaced by those of a random panel profile (drawn per slot and rollout,
  task fields kept), the teacher's action under it stored beside it. Every minibatch then runs
  the actor again on the same sequences with the swapped condition in the observation and adds
  ``style_pair_coef`` x the mean NLL of those labels. PPO only sees the style an agent drives
  under, so it has no reason to keep the actions of the other styles apart; the paired term
  pins how the action changes with the style at the states PPO visits.

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
from cpalgo.policies import sequence_lengths

__all__ = ["TeacherPPO", "export_recurrent_ppo"]


class TeacherPPO(HookedPPO):
    """Self-play PPO with the teacher's actions as an auxiliary imitation term (module docstring).

    Args:
        teacher: ``reactive`` (:class:`cpsim.expert.ReactiveExpert`, default) or ``tracking``.
        teacher_coef: weight of the imitation term at the start (1.0).
        teacher_coef_final: its weight at the end of ``learn`` (None: ``teacher_coef``).
        style_pairs: K swapped-style labels per live decision (0: off; module docstring).
        style_pair_coef: weight of their imitation term (None: the current ``teacher_coef``).
        style_pair_focus: average that term only over the decisions whose swapped label differs
            from the agent's own label (the ones that need the condition to be told apart); by
            default over every live decision, where the pairs with equal labels repeat the main term.
        Other arguments: :class:`cpalgo.common.hooked_train.HookedPPO`'s and PPO's.
    """

    _RUNTIME_ATTRS: ClassVar[tuple[str, ...]] = HookedPPO._RUNTIME_ATTRS + ("_teacher", "_nll_raw", "_agree_raw",
                                                                         "_pair_raw", "_differ_raw", "_swap_profiles",
                                                                         "_swap_rng")

    def __init__(self, policy: Any, env: Any, teacher: str = "reactive", teacher_coef: float = 1.0,
                 teacher_coef_final: float | None = None, style_pairs: int = 0,
                 style_pair_coef: float | None = None, style_pair_focus: bool = False, **kwargs: Any) -> None:
        self.teacher = teacher
        self.teacher_coef = teacher_coef
        self.teacher_coef_final = teacher_coef_final
        self.style_pairs = style_pairs
        self.style_pair_coef = style_pair_coef
        self.style_pair_focus = style_pair_focus
        super().__init__(policy, env, **kwargs)

    def _validate_settings(self) -> None:
        super()._validate_settings()
        from cpsim.expert import EXPERTS

        if self.teacher not in EXPERTS:
            raise ValueError(f"teacher: unknown teacher {self.teacher!r}; accepted: {list(EXPERTS)}")
        check_number("teacher_coef", self.teacher_coef, low=0.0)
        if self.teacher_coef_final is not None:
            check_number("teacher_coef_final", self.teacher_coef_final, low=0.0)
        check_number("style_pairs", self.style_pairs, low=0, integer=True)
        if self.style_pair_coef is not None:
            check_number("style_pair_coef", self.style_pair_coef, low=0.0)
        if not isinstance(self.style_pair_focus, (bool, np.bool_)):
            raise ValueError(f"style_pair_focus: must be True or False, got {self.style_pair_focus!r}")
        if self.style_pairs and self.teacher == "tracking":
            raise ValueError("style_pairs: the tracking teacher ignores the style, so its swapped labels would "
                             "teach nothing; use a reactive teacher")

    def _extra_shapes(self) -> dict[str, tuple[int, ...]]:
        shapes: dict[str, tuple[int, ...]] = {"teacher_action": ()}
        if self.style_pairs:
            from cpsim.conditions import CONDITION_FIELDS

            shapes["swap_action"] = (int(self.style_pairs),)
            shapes["swap_condition"] = (int(self.style_pairs), len(CONDITION_FIELDS))
        return shapes

    def _reset_runtime(self) -> None:
        super()._reset_runtime()
        self._teacher: Any = None
        self._nll_raw: list[float] = []
        self._agree_raw: list[float] = []
        self._pair_raw: list[float] = []
        self._differ_raw: list[float] = []
        self._swap_profiles: np.ndarray | None = None
        self._swap_rng = np.random.default_rng(None if self.seed is None else int(self.seed) + 7919)

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
        if self.style_pairs:
            self._label_swapped_styles(sim, rows)
        return out

    def _label_swapped_styles(self, sim: Any, rows: np.ndarray) -> None:
        """Store, for the live ``rows``, K swapped conditions (K, 10) raw and the teacher's
        action under each (the world itself drives on under its own conditions)."""
        from cpsim.conditions import PANEL, with_panel_styles
        from cpsim.expert import actions_under

        own = sim.conditions.reshape(-1, sim.conditions.shape[-1]).cpu().numpy()  # (W * A, 10)
        pos = self.rollout_buffer.pos
        if pos == 0 or self._swap_profiles is None or self._swap_profiles.shape[1] != own.shape[0]:
            self._swap_profiles = self._swap_rng.integers(0, len(PANEL), size=(int(self.style_pairs), own.shape[0]))
        teacher = self._teacher_for(sim)
        extras = self.rollout_buffer.extras
        for k in range(int(self.style_pairs)):
            cond = with_panel_styles(own, self._swap_profiles[k])
            extras["swap_action"][pos, rows, k] = actions_under(teacher, th.as_tensor(cond)).reshape(-1).cpu().numpy()[rows]
            extras["swap_condition"][pos, rows, k] = cond[rows]

    # ------------------------------------------------------------------ loss
    def _minibatch_terms(self, rollout_data: Any, mask: th.Tensor, logits: th.Tensor) -> dict[str, th.Tensor]:
        target = self.rollout_buffer.sample_extras["teacher_action"].reshape(-1).long()  # (n,)
        logp = th.log_softmax(logits.float(), dim=-1)
        nll = -logp.gather(-1, target[:, None]).squeeze(-1)
        value = masked_mean(nll, mask)
        with th.no_grad():
            self._nll_raw.append(float(value.item()))
            self._agree_raw.append(float(masked_mean((logits.argmax(-1) == target).float(), mask).item()))
        terms = {"teacher_nll_loss": self.current_teacher_coef() * value}
        if self.style_pairs:
            pair = self._style_pair_nll(rollout_data, mask)
            coef = self.current_teacher_coef() if self.style_pair_coef is None else float(self.style_pair_coef)
            terms["style_pair_nll_loss"] = coef * pair
        return terms

    def _style_pair_nll(self, rollout_data: Any, mask: th.Tensor) -> th.Tensor:
        """Mean NLL (scalar, with grad) of the swapped-style labels, the actor re-run on the
        minibatch's sequences with each swapped condition in the observation."""
        extras = self.rollout_buffer.sample_extras
        conditions, targets = extras["swap_condition"], extras["swap_action"].long()  # (n, K, 10), (n, K)
        own = extras["teacher_action"].reshape(-1, 1).long()
        differ = (targets != own) & mask[:, None]  # (n, K)
        self._differ_raw.append(float(differ.float().sum() / mask.float().sum().clamp(min=1.0) / targets.shape[1]))
        layout = base_vec_env(self.env).sim.obs_layout
        keep = mask.to(rollout_data.observations.dtype)[:, None]
        total = th.zeros((), device=mask.device)
        for k in range(int(self.style_pairs)):
            obs = layout.replace_condition(rollout_data.observations, conditions[:, k]) * keep
            with sequence_lengths(self.policy, mask, rollout_data.lstm_states.pi[0].shape[1]):
                dist, _ = self.policy.get_distribution(obs, rollout_data.lstm_states.pi, rollout_data.episode_starts)
            logp = th.log_softmax(dist.distribution.logits.float(), dim=-1)
            counted = differ[:, k] if self.style_pair_focus else mask
            total = total + masked_mean(-logp.gather(-1, targets[:, k, None]).squeeze(-1), counted)
        value = total / int(self.style_pairs)
        self._pair_raw.append(float(value.item()))
        return value

    def _after_train(self) -> None:
        if self._nll_raw:
            self.logger.record("train/teacher_nll", float(np.mean(self._nll_raw)))
            self.logger.record("train/teacher_agreement", float(np.mean(self._agree_raw)))
            self.logger.record("train/teacher_coef", self.current_teacher_coef())
        if self._pair_raw:
            self.logger.record("train/style_pair_nll", float(np.mean(self._pair_raw)))
            self.logger.record("train/style_pair_differ", float(np.mean(self._differ_raw)))
        self._nll_raw, self._agree_raw, self._pair_raw, self._differ_raw = [], [], [], []
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
