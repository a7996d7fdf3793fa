"""CL4AD-dagger's learnability curriculum over the training scenarios.

:class:`LearnabilitySampler` keeps a running success estimate per scenario (exponentially
decayed counts of agent episodes that reached their goal, with a Beta(1, 1) prior, so an
unseen scenario is estimated at 0.5) and samples scenarios with probability

    P(s) = (1 - uniform) * L(s)^(1 / temperature) / sum_s' L(s')^(1 / temperature) + uniform / S,
    L(s) = p(s) (1 - p(s)),

the *learnability* of a scenario: largest (0.25) where the policy completes it half of the
time, zero where it always or never does. :class:`CurriculumReset` makes a
:class:`cpsim.SelfPlayVecEnv` reset its worlds into sampled scenarios: the env resets a world
as usual (its own scenario and p_train condition draws), and the world is then reset again
into the curriculum's scenario with the conditions just drawn.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["LearnabilitySampler", "CurriculumReset"]


class LearnabilitySampler:
    """Scenario sampling by learnability (see the module docstring).

    Args:
        num_scenarios: S, scenarios of the pool.
        temperature: > 0; smaller concentrates on the most learnable scenarios (0.5).
        uniform: share of uniform sampling in [0, 1] (0.2), so every scenario keeps being
            visited and its estimate stays current.
        decay: factor applied to a scenario's counts at each of its episodes, in (0, 1]
            (0.9: the estimate follows the last ~10 agent episodes of that scenario).
        seed: seed of the draws.
    """

    def __init__(self, num_scenarios: int, temperature: float = 0.5, uniform: float = 0.2, decay: float = 0.9,
                 seed: int = 0) -> None:
        if int(num_scenarios) < 1:
            raise ValueError(f"num_scenarios: must be >= 1, got {num_scenarios!r}")
        self.num_scenarios = int(num_scenarios)
        self.temperature = float(temperature)
        self.uniform = float(uniform)
        self.decay = float(decay)
        self.successes = np.zeros(self.num_scenarios, np.float64)
        self.episodes = np.zeros(self.num_scenarios, np.float64)
        self.rng = np.random.default_rng(int(seed))

    def update(self, scenarios: np.ndarray, success: np.ndarray) -> None:
        """Record finished agent episodes: ``scenarios`` (n,) int, ``success`` (n,) bool, in order."""
        for s, ok in zip(np.asarray(scenarios, np.int64).tolist(), np.asarray(success, bool).tolist()):
            self.successes[s] = self.decay * self.successes[s] + float(ok)
            self.episodes[s] = self.decay * self.episodes[s] + 1.0

    @property
    def success_rate(self) -> np.ndarray:
        """(S,) posterior mean success estimate (Beta(1, 1) prior)."""
        return (self.successes + 1.0) / (self.episodes + 2.0)

    @property
    def learnability(self) -> np.ndarray:
        """(S,) p (1 - p)."""
        p = self.success_rate
        return p * (1.0 - p)

    def probabilities(self) -> np.ndarray:
        """(S,) sampling probabilities."""
        score = self.learnability ** (1.0 / self.temperature)
        total = score.sum()
        focus = score / total if total > 0 else np.full(self.num_scenarios, 1.0 / self.num_scenarios)
        return (1.0 - self.uniform) * focus + self.uniform / self.num_scenarios

    def sample(self, n: int) -> np.ndarray:
        """(n,) scenario indices."""
        return self.rng.choice(self.num_scenarios, size=int(n), p=self.probabilities()).astype(np.int64)

    def state(self) -> dict[str, list[float]]:
        return {"successes": self.successes.tolist(), "episodes": self.episodes.tolist()}

    def load_state(self, state: dict[str, list[float]]) -> None:
        self.successes = np.asarray(state["successes"], np.float64)
        self.episodes = np.asarray(state["episodes"], np.float64)


class CurriculumReset:
    """Routes a :class:`cpsim.SelfPlayVecEnv`'s world resets through a sampler.

    ``install`` replaces the env object's ``_reset_worlds`` by a wrapper (the env class is
    untouched); ``remove`` puts the original back.

    Args:
        env: the self-play env (innermost VecEnv).
        choose: ``n -> (n,) scenario indices``.
    Attributes:
        resets: (S,) how many world resets went to each scenario.
    """

    def __init__(self, env: Any, choose: Callable[[int], np.ndarray]) -> None:
        self.env = env
        self.choose = choose
        self.resets = np.zeros(len(env.scenarios), np.int64)
        self._original = None

    def install(self) -> None:
        if self._original is not None:
            return
        original = self.env._reset_worlds
        sim = self.env.sim

        def reset_worlds(worlds: np.ndarray) -> None:
            worlds = np.asarray(worlds, np.int64)
            original(worlds)  # the env's own draws (scenario, p_train conditions) stay in sequence
            if worlds.size == 0:
                return
            scenarios = np.asarray(self.choose(worlds.size), np.int64)
            conditions = sim.conditions[worlds].detach().cpu().numpy().copy() if hasattr(sim.conditions, "detach") \
                else np.asarray(sim.conditions)[worlds].copy()
            sim.reset(worlds=worlds, scenario_index=scenarios, conditions=conditions)
            np.add.at(self.resets, scenarios, 1)

        self._original = original
        self.env._reset_worlds = reset_worlds

    def remove(self) -> None:
        if self._original is not None:
            self.env.__dict__.pop("_reset_worlds", None)
            self._original = None
