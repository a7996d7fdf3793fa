"""PlannerRFT-dagger's exploration head: a small Gaussian policy over the log sampling
temperature of a continuation, given the focal agent's observation at the root."""

from __future__ import annotations

import math

import torch as th
from torch import nn

__all__ = ["ExplorationHead"]


class ExplorationHead(nn.Module):
    """``obs (n, D) -> Normal(mean (n,), std (n,))`` over ``x = log temperature``.

    The temperature used is ``exp(clip(x, log t_min, log t_max))``; PPO treats ``x`` as the
    action (the clip is the environment's, as SB3 clips Box actions).

    Args:
        obs_size: D.
        hidden: width of the hidden layer.
        init_std: initial standard deviation of ``x`` (> 0).
    At initialisation the mean is exactly 0 (temperature 1: the policy's own distribution).
    """

    def __init__(self, obs_size: int, hidden: int = 32, init_std: float = 0.3) -> None:
        super().__init__()
        if obs_size < 1 or hidden < 1 or not init_std > 0:
            raise ValueError(f"obs_size, hidden must be >= 1 and init_std > 0, got {obs_size}, {hidden}, {init_std}")
        self.net = nn.Sequential(nn.Linear(obs_size, hidden), nn.Tanh(), nn.Linear(hidden, 1))
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)
        self.log_std = nn.Parameter(th.tensor(math.log(init_std), dtype=th.float32))

    def forward(self, obs: th.Tensor) -> th.distributions.Normal:
        mean = self.net(obs).squeeze(-1)
        return th.distributions.Normal(mean, self.log_std.exp().expand_as(mean))
