"""CL4AD adapted to reward-conditioned self-play (the seed paper's CL4AD-dagger baseline).

The original (Koprulu et al., 2026) replaces uniform scenario sampling during driving-policy
training by a curriculum that favours scenarios of high *learnability*: those the current
policy sometimes completes and sometimes fails.

Adaptation (:class:`CL4AD`): PPO-Continue whose self-play worlds reset into scenarios drawn
by :class:`cpalgo.baselines.cl4ad.curriculum.LearnabilitySampler` instead of uniformly. Every POLICY
agent's finished episode (goal or not; worlds cut at the deadline count as timeouts)
updates the running success estimate of the scenario its world was running. Conditions
are still drawn per agent from p_train at every reset (the anchor's distribution), so the
curriculum changes only *where* self-play happens. The budget is the main rollout's live
transitions, as for PPO-Continue.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch as th
from sb3_contrib.common.recurrent.type_aliases import RNNStates

from cpalgo.baselines.cl4ad.curriculum import CurriculumReset, LearnabilitySampler
from cpalgo.common.hooked_train import HookedPPO, check_number
from cpalgo.counterplay.driver import outcome_code
from cpalgo.methods.base import base_vec_env
from cpsim.config import Outcome

__all__ = ["CL4AD"]


class CL4AD(HookedPPO):
    """CL4AD-dagger (see the module docstring).

    Args:
        curriculum_temperature: sharpness of the learnability weights, > 0 (0.5).
        curriculum_uniform: share of uniform scenario sampling, in [0, 1] (0.2).
        success_decay: decay of a scenario's success counts per episode, in (0, 1] (0.9).
        Other arguments: :class:`cpalgo.common.hooked_train.HookedPPO`'s and PPO's.

    Attributes:
        sampler: the :class:`LearnabilitySampler` (its counts are saved with the model).
        curriculum_totals: running ``agent_episodes`` and ``agent_successes``.
    """

    _RUNTIME_ATTRS: ClassVar[tuple[str, ...]] = HookedPPO._RUNTIME_ATTRS + ("_curriculum", "_episode_scenario")

    def __init__(self, policy: Any, env: Any, curriculum_temperature: float = 0.5, curriculum_uniform: float = 0.2,
                 success_decay: float = 0.9, **kwargs: Any) -> None:
        self.curriculum_temperature = curriculum_temperature
        self.curriculum_uniform = curriculum_uniform
        self.success_decay = success_decay
        self.sampler: LearnabilitySampler | None = None
        self.curriculum_totals: dict[str, int] = {}
        self._curriculum: CurriculumReset | None = None
        super().__init__(policy, env, **kwargs)

    def _validate_settings(self) -> None:
        super()._validate_settings()
        check_number("curriculum_temperature", self.curriculum_temperature, low=0.0, low_open=True)
        check_number("curriculum_uniform", self.curriculum_uniform, low=0.0, high=1.0)
        check_number("success_decay", self.success_decay, low=0.0, high=1.0, low_open=True)

    def _reset_runtime(self) -> None:
        super()._reset_runtime()
        self._episode_scenario: np.ndarray | None = None

    def _setup_model(self) -> None:
        super()._setup_model()
        self._install_curriculum()

    def set_env(self, env: Any, force_reset: bool = True) -> None:
        if self._curriculum is not None:
            self._curriculum.remove()
            self._curriculum = None
        super().set_env(env, force_reset=force_reset)
        self._install_curriculum()

    def _install_curriculum(self) -> None:
        if self.env is None:
            return
        base = base_vec_env(self.env)
        if not hasattr(base, "_reset_worlds") or not hasattr(base, "scenarios"):
            raise ValueError(f"env: CL4AD needs a cpsim.SelfPlayVecEnv (worlds it can reset), got {type(base).__name__}")
        n = len(base.scenarios)
        if self.sampler is None or self.sampler.num_scenarios != n:
            self.sampler = LearnabilitySampler(n, float(self.curriculum_temperature), float(self.curriculum_uniform),
                                               float(self.success_decay), seed=int(self.seed or 0) + 2038074743)
        if self._curriculum is None or self._curriculum.env is not base:
            self._curriculum = CurriculumReset(base, lambda k: self.sampler.sample(k))
            self._curriculum.install()

    # ------------------------------------------------------------------ rollout
    def _policy_step(self, env: Any, obs_tensor: th.Tensor, lstm_states: RNNStates, episode_starts: th.Tensor
                     ) -> tuple[th.Tensor, th.Tensor, th.Tensor, RNNStates]:
        sim = base_vec_env(env).sim
        ws = sim.world_scenario
        self._episode_scenario = (ws.detach().cpu().numpy() if hasattr(ws, "detach") else np.asarray(ws)).astype(np.int64)
        return super()._policy_step(env, obs_tensor, lstm_states, episode_starts)

    def _after_env_step(self, env: Any, dones: np.ndarray, infos: list[dict]) -> tuple[np.ndarray, np.ndarray | None]:
        was_active = self._last_active
        if was_active is not None and self._episode_scenario is not None and self.sampler is not None:
            a = int(base_vec_env(env).max_agents)
            ended = np.flatnonzero(np.asarray(dones, bool) & was_active)
            codes = np.array([outcome_code(infos[i].get("outcome")) for i in ended.tolist()], np.int64)
            real = codes >= 0  # empty slots carry no outcome
            if real.any():
                idx = ended[real]
                success = codes[real] == int(Outcome.GOAL)
                self.sampler.update(self._episode_scenario[idx // a], success)
                self.curriculum_totals["agent_episodes"] = self.curriculum_totals.get("agent_episodes", 0) + int(idx.size)
                self.curriculum_totals["agent_successes"] = (self.curriculum_totals.get("agent_successes", 0)
                                                             + int(success.sum()))
        return super()._after_env_step(env, dones, infos)

    def _after_train(self) -> None:
        super()._after_train()
        if self.sampler is not None:
            p = self.sampler.probabilities()
            self.logger.record("curriculum/max_probability", float(p.max()))
            self.logger.record("curriculum/mean_success", float(self.sampler.success_rate.mean()))
        for key, value in self.curriculum_totals.items():
            self.logger.record(f"curriculum/{key}", value)
