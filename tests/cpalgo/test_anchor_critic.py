"""cpalgo.anchor.critic: the critic's value over the 2 s before each failure."""

from __future__ import annotations

import pytest
import torch as th
from sb3_contrib import RecurrentPPO

from cpalgo.anchor.critic import value_before_failures
from cpalgo.policies import BehaviorLstmPolicy
from cpsim import SelfPlayVecEnv
from cpsim.scenario import eval_pool


class _Clock(th.nn.Module):
    """Wraps a policy; its value is ``sign x (decisions so far)``: falling or rising by construction."""

    def __init__(self, policy, sign: float):
        super().__init__()
        self.inner, self.sign, self.t = policy, sign, 0
        self.lstm_actor = policy.lstm_actor

    def forward(self, obs, states, starts, deterministic=False):
        actions, values, log_prob, states = self.inner(obs, states, starts, deterministic=deterministic)
        self.t += 1
        return actions, th.full_like(values, self.sign * self.t), log_prob, states


@pytest.fixture(scope="module")
def model():
    env = SelfPlayVecEnv(num_worlds=1, max_agents=4, seed=0, dynamics="classic", num_scenarios=2)
    return RecurrentPPO(BehaviorLstmPolicy, env, n_steps=8, batch_size=32, seed=0,
                        policy_kwargs=dict(lstm_hidden_size=16))


def test_falls_counts_failures_whose_value_dropped(model):
    tasks = eval_pool(6, seed=0)
    config = {"dynamics": "classic"}
    real = model.policy
    try:
        model.policy = _Clock(real, -1.0)
        down = value_before_failures(model, tasks, config=config, horizon=5)
        model.policy = _Clock(real, +1.0)
        up = value_before_failures(model, tasks, config=config, horizon=5)
    finally:
        model.policy = real
    assert down.failures > 0 and down.failures == up.failures
    assert down.falls == 1.0 and up.falls == 0.0
    assert down.mean_change == pytest.approx(-5.0) and up.mean_change == pytest.approx(5.0)
    assert sum(v["failures"] for v in down.per_outcome.values()) == down.failures
    trend = value_before_failures(model, tasks, config=config, horizon=5)  # the real critic
    assert 0.0 <= trend.falls <= 1.0 and trend.failures == down.failures
    with pytest.raises(ValueError, match="horizon"):
        value_before_failures(model, tasks, horizon=0)


def test_the_check_leaves_the_callers_rng_alone(model):
    th.manual_seed(123)
    before = th.get_rng_state()
    value_before_failures(model, eval_pool(2, seed=0), config={"dynamics": "classic"}, horizon=5)
    assert th.equal(th.get_rng_state(), before)
