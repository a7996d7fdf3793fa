"""VinePPO adapted to recurrent self-play driving (the seed paper's VinePPO-dagger baseline).

The original (Kazemnejad et al., 2025) drops PPO's value network for language-model
reasoning: at intermediate states of each sampled answer it resets the generator and
samples ``K`` independent completions, and the mean of their returns is a Monte Carlo
estimate of the state's value. Advantages use those estimates instead of a learned critic.

Adaptation (:class:`VinePPO`): the states are the main self-play rollout's interaction
states (the ego approaches another vehicle, :mod:`cpalgo.baselines.continuations`, the same
roots and groups as DAPO-dagger): from each, ``group_size`` (1 + 5) independent
closed-loop continuations run to the original deadline, co-players reacting, with the
rollout's own policy (they run right after the rollout, before its advantages are
computed). The critic's value at the root decision is replaced by the mean discounted
return of the continuations (bootstrapped with the critic only where the focal task is cut
at the deadline, as the main rollout's truncated episodes are), and PPO's GAE advantages
and value targets of the rollout are computed with it. Elsewhere the critic stays: a
simulator step is far dearer than a token, so only the roots get Monte Carlo values.
The continuations themselves are not trained on (VinePPO uses them for values only).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cpalgo.baselines.continuations import ContinuationPPO, ContinuationRoot, GroupResult

__all__ = ["VinePPO"]


class VinePPO(ContinuationPPO):
    """VinePPO-dagger (see the module docstring).

    Takes :class:`cpalgo.baselines.continuations.ContinuationPPO`'s arguments (group size,
    trigger, allowance) and PPO's; ``group_coef`` is unused (no group objective).

    Attributes:
        vine_values: per root of the last generation: ``buffer_pos``, ``env_index``, the
            critic's ``critic_value`` and the Monte Carlo ``mc_value`` that replaced it.
        continuation_totals: also ``values_replaced`` and ``abs_value_change`` (summed
            |MC - critic|).
    """

    def __init__(self, policy: Any, env: Any, **kwargs: Any) -> None:
        self.vine_values: list[dict[str, float]] = []
        super().__init__(policy, env, **kwargs)

    def _use_groups(self, roots: list[ContinuationRoot], results: list[GroupResult]) -> None:
        values = self.rollout_buffer.values  # (n_steps, n_envs), GAE has not read it yet
        self.vine_values = []
        for root, res in zip(roots, results):
            critic = float(values[root.buffer_pos, root.env_index])
            mc = float(np.mean(res.returns))
            values[root.buffer_pos, root.env_index] = mc
            self.vine_values.append({"buffer_pos": root.buffer_pos, "env_index": root.env_index,
                                     "critic_value": critic, "mc_value": mc})
            self._bump("values_replaced")
            self._bump("abs_value_change", abs(mc - critic))
