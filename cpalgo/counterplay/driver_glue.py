"""CounterPlay's link to its search driver (:class:`~cpalgo.counterplay.driver.SearchDriver`).

:class:`SearchDriverMixin` is one of :class:`~cpalgo.counterplay.algorithm.CounterPlay`'s
bases: it builds the driver from the settings and the budget and attaches it to the env and
policy (``_ensure_driver``; under a ``VecNormalize`` wrapper the driver's branch
observations get its normalisation), keeps the searches of each wave
(:func:`~cpalgo.counterplay.records.keep_wave`), and exposes the driver's statistics
(``search_stats``), root replays (``replay_root``) and the per-generation log
(``_log_generation``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch as th
from stable_baselines3.common.vec_env import VecEnv, unwrap_vec_normalize

from cpalgo.counterplay.driver import SearchDriver, SearchStats
from cpalgo.counterplay.records import keep_wave

if TYPE_CHECKING:
    from cpalgo.counterplay.branches import BranchResult

__all__ = ["SearchDriverMixin"]


class SearchDriverMixin:
    """The search driver of a CounterPlay model (see the module docstring)."""

    @property
    def _branching(self) -> bool:
        return self.counterfactual and self.env is not None

    @property
    def search_stats(self) -> SearchStats:
        """Search counts of the last generation (empty before the first one)."""
        return self._driver.stats if self._driver is not None else SearchStats()

    def _ensure_driver(self, env: VecEnv) -> None:
        if self._driver is None:
            def count(n: int) -> None:
                self.num_timesteps += int(n)

            self._driver = SearchDriver(self._search_settings(), self.budget, self.device, count_transitions=count)
            self._driver.on_wave = lambda *wave: keep_wave(self, *wave)
        transform = None
        vec_normalize = unwrap_vec_normalize(env)
        if vec_normalize is not None:
            def transform(obs: th.Tensor) -> th.Tensor:
                return th.as_tensor(vec_normalize.normalize_obs(obs.cpu().numpy()), device=obs.device)
        self._driver.attach(env, self.policy, transform)

    def replay_root(self, world: int, root_step: int, main_draws: bool = True) -> BranchResult:
        """Re-run a stored root of ``world``'s current episode as one factual branch.

        With ``main_draws`` the branch samples every decision from the uniforms the main
        rollout used (fresh draws once those run out), so it reproduces the recorded
        actions and trajectory: the check that branches start from the true state. That
        holds for a root recorded since the policy's last update; a root of the previous
        rollout (kept with ``root_lifetime="episode"``) replays under the updated policy.
        Returns the :class:`BranchResult` (``actions`` (1, T, A), ``xy`` (1, T + 1, A, 2)).
        """
        if self._driver is None:
            raise ValueError("world: no roots recorded yet (counterfactual=True and a rollout are needed)")
        return self._driver.replay_root(self.policy, world, root_step, main_draws)

    def _log_generation(self, summary: dict[str, int]) -> None:
        if not self.counterfactual:
            return
        self.search_stats.record(self.logger.record, self.panel, self.verify)
        gen_total = summary["main"] + summary["branch"]
        self.logger.record("counterplay/branch_share", summary["branch"] / gen_total if gen_total else 0.0)
        for key in ("main", "factual", "candidate", "verification", "total"):
            self.logger.record(f"counterplay/budget_{key}", getattr(self.budget, key))
