"""The hooks of CounterPlay's rollout loop (:meth:`CounterPlay.collect_rollouts
<cpalgo.counterplay.algorithm.CounterPlay.collect_rollouts>`, sb3-contrib's loop with hook
points): what runs at a rollout's start and end, at each decision and after each env step.

:class:`RolloutHooksMixin` is one of :class:`~cpalgo.counterplay.algorithm.CounterPlay`'s
bases. Its hooks count B_post (``_counted_transitions``, ``budget``), keep the activity mask
of the live slots (``_observed_active``, ``_active_index``; inference on live slots only),
bootstrap truncated episodes (``_bootstrap_timeouts``) and hand roots, failures and the end
of a generation to the search driver (:mod:`cpalgo.counterplay.driver_glue`). The methods
of :mod:`cpalgo.methods` and :mod:`cpalgo.baselines` override them.
"""

from __future__ import annotations

import numpy as np
import torch as th
from gymnasium import spaces
from sb3_contrib.common.recurrent.type_aliases import RNNStates
from stable_baselines3.common.vec_env import VecEnv

from cpalgo.common.policy_utils import put_states, take_states

__all__ = ["RolloutHooksMixin"]


class RolloutHooksMixin:
    """The rollout loop's hooks and live-slot bookkeeping (see the module docstring)."""

    def _on_env_reset(self) -> None:
        """Called when ``learn`` reset the env: fresh activity mask, stale roots dropped."""
        assert self.env is not None
        self._last_active = self._observed_active(self.env, getattr(self.env, "reset_infos", None))
        if self._branching:
            self._ensure_driver(self.env)
        if self._driver is not None:
            self._driver.on_env_reset()

    def _rollout_start(self, env: VecEnv) -> None:
        self.budget.start_generation()
        if self._last_active is None:
            self._last_active = self._observed_active(env, None)
        if self._branching:
            self._ensure_driver(env)
            self._driver.start_rollout()
        self._set_phase("rollout")

    def _policy_step(
        self, env: VecEnv, obs_tensor: th.Tensor, lstm_states: RNNStates, episode_starts: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor, RNNStates]:
        """One decision of every slot: the search driver's (roots, recorded draws) when
        branching, else ``policy.forward`` on the live slots only (inactive slots get
        action 0, value 0, log-prob 0, which the masked buffer never uses)."""
        n = obs_tensor.shape[0]
        idx = self._active_index(n)
        if self._branching:
            assert self._driver is not None
            return self._driver.policy_step(env.sim, self.policy, obs_tensor, lstm_states, episode_starts, idx)
        if idx is None:
            return self.policy(obs_tensor, lstm_states, episode_starts)
        actions, values, log_probs, states = self.policy(obs_tensor[idx], take_states(lstm_states, idx),
                                                         episode_starts[idx])
        full_actions = th.zeros((n, *actions.shape[1:]), dtype=actions.dtype, device=self.device)
        full_values = th.zeros((n, *values.shape[1:]), dtype=values.dtype, device=self.device)
        full_log_probs = th.zeros(n, dtype=log_probs.dtype, device=self.device)
        full_actions[idx], full_values[idx], full_log_probs[idx] = actions, values, log_probs
        return full_actions, full_values, full_log_probs, put_states(lstm_states, idx, states)

    def _counted_transitions(self, env: VecEnv) -> int:
        """Transitions of the step just taken that count toward B_post: the slots that were
        live before it (every slot without masking, which is SB3's count)."""
        if not self.mask_inactive or self._last_active is None:
            return env.num_envs
        return int(np.count_nonzero(self._last_active))

    def _bootstrap_timeouts(self, rewards: np.ndarray, dones: np.ndarray, infos: list[dict], lstm_states: RNNStates) -> None:
        """Add gamma * V(terminal obs) to truncated episodes' last reward.

        Features off: the parent's per-index code (bit-identical), visiting only done
        indices. Otherwise one batched critic pass over every truncated index.
        """
        done_idx = np.flatnonzero(dones)
        if done_idx.size == 0:
            return
        truncated = [
            idx for idx in done_idx.tolist()
            if infos[idx].get("terminal_observation") is not None and infos[idx].get("TimeLimit.truncated", False)
        ]
        if not truncated:
            return
        batched = (self.counterfactual or self.mask_inactive) and not isinstance(self.observation_space, spaces.Dict)
        if not batched:
            for idx in truncated:
                terminal_obs = self.policy.obs_to_tensor(infos[idx]["terminal_observation"])[0]
                with th.no_grad():
                    terminal_lstm_state = (
                        lstm_states.vf[0][:, idx : idx + 1, :].contiguous(),
                        lstm_states.vf[1][:, idx : idx + 1, :].contiguous(),
                    )
                    episode_starts = th.tensor([False], dtype=th.float32, device=self.device)
                    terminal_value = self.policy.predict_values(terminal_obs, terminal_lstm_state, episode_starts)[0]
                rewards[idx] += self.gamma * terminal_value
            return
        idx = np.asarray(truncated, np.int64)
        terminal_obs = np.stack([infos[i]["terminal_observation"] for i in truncated])
        with th.no_grad():
            obs_t = self.policy.obs_to_tensor(terminal_obs)[0]
            sel = th.as_tensor(idx, device=self.device)
            state = (lstm_states.vf[0][:, sel].contiguous(), lstm_states.vf[1][:, sel].contiguous())
            starts = th.zeros(idx.size, dtype=th.float32, device=self.device)
            terminal_values = self.policy.predict_values(obs_t, state, starts).reshape(-1).cpu().numpy()
        rewards[idx] += (self.gamma * terminal_values).astype(rewards.dtype)

    def _after_env_step(self, env: VecEnv, dones: np.ndarray, infos: list[dict]) -> tuple[np.ndarray, np.ndarray | None]:
        """Budget count, failures -> search requests, episode bookkeeping.

        Returns the new activity mask and the slots revived without a done (or None).
        """
        assert self._last_active is not None
        was_active = self._last_active
        self.budget.add_main(int(np.count_nonzero(was_active)))
        new_active = self._observed_active(env, infos)
        if self._branching:
            assert self._driver is not None
            self._driver.after_step(env.sim, dones, infos, was_active)
        revived = None
        if self.mask_inactive:
            revived = new_active & ~was_active & ~np.asarray(dones, bool)
        return new_active, revived

    def _rollout_end(self, env: VecEnv) -> None:
        """Finish the previous generation's searches (their teachers go to this update)
        and queue this generation's for the next rollout."""
        if self._driver is not None and self._branching:
            self._set_phase("search")
            self._driver.end_rollout(self.policy, self.budget.generation_main)
            self._teachers = self._driver.take_teachers()
            stats = self._driver.stats
            for key, value in stats.as_dict().items():
                self.search_totals[key] = self.search_totals.get(key, 0) + value
        summary = self.budget.end_generation()
        self._log_generation(summary)
        self._set_phase("train")

    @property
    def stops_exactly(self) -> bool:
        """Whether ``learn`` cuts its last rollout at the step that reaches the budget: with
        ``post_budget`` set (every registered method's ``learn(B)``). Without it, ``learn``
        runs whole generations, as the parent does."""
        return self.budget.post_budget is not None

    def _observed_active(self, env: VecEnv, infos: list[dict] | None) -> np.ndarray:
        """(num_envs,) bool: slots whose current observation belongs to a live agent."""
        if hasattr(env, "active_mask"):
            return np.asarray(env.active_mask(), bool).reshape(-1)
        if infos is not None and infos and "active" in infos[0]:
            return np.fromiter((bool(i.get("active", True)) for i in infos), bool, count=len(infos))
        return np.ones(env.num_envs, bool)

    def _active_index(self, n: int) -> th.Tensor | None:
        """Indices of the live slots, or None when inference runs on every slot."""
        active = self._last_active
        if not self.mask_inactive or active is None or active.size != n or active.all():
            return None
        return th.as_tensor(np.flatnonzero(active), device=self.device)
