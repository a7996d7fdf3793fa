"""CounterPlay without a simulator: parent equivalence, masking, arguments, budget, save/load."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from sb3_contrib import RecurrentPPO
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from stable_baselines3.common.env_util import make_vec_env

from cpalgo import CounterPlay
from cpalgo.counterplay.budget import Budget
from tests.cpalgo.fakes import SlotVecEnv

SMALL = dict(n_steps=32, batch_size=32, n_epochs=2, device="cpu",
             policy_kwargs=dict(lstm_hidden_size=16, net_arch=[16]))
OFF = dict(counterfactual=False, mask_inactive=False)


pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def _params(model) -> dict[str, th.Tensor]:
    return {k: v.detach().clone() for k, v in model.policy.state_dict().items()}


def test_features_off_is_bit_identical_to_recurrent_ppo():
    env = make_vec_env("CartPole-v1", n_envs=2, seed=3)
    parent = RecurrentPPO("MlpLstmPolicy", env, seed=3, **SMALL)
    init = _params(parent)
    parent.learn(256)
    env = make_vec_env("CartPole-v1", n_envs=2, seed=3)
    # "MlpLstmPolicy" means the fused policy for CounterPlay; the stock class is the reference
    child = CounterPlay(RecurrentActorCriticPolicy, env, seed=3, **OFF, **SMALL).learn(256)
    a, b = _params(parent), _params(child)
    assert a.keys() == b.keys()
    assert all(th.equal(a[k], b[k]) for k in a)
    assert not all(th.equal(a[k], init[k]) for k in a)  # learning actually happened
    assert child.num_timesteps == parent.num_timesteps


def _train_on_slots(garbage_seed: int, mask_inactive: bool) -> dict[str, th.Tensor]:
    model = CounterPlay("MlpLstmPolicy", SlotVecEnv(garbage_seed), counterfactual=False, mask_inactive=mask_inactive,
                        seed=1, n_steps=24, batch_size=32, n_epochs=2, device="cpu",
                        policy_kwargs=dict(lstm_hidden_size=8, net_arch=[8]))
    model.learn(24 * 4 * 3)
    return _params(model)


def test_inactive_slots_do_not_change_the_update():
    # the inactive slots' observations and rewards are different random garbage in the
    # two runs: with masking the learned parameters must not depend on it at all
    a, b = _train_on_slots(0, True), _train_on_slots(1, True)
    assert all(th.equal(a[k], b[k]) for k in a)
    # without masking the garbage leaks into the losses and advantage normalisation
    c, d = _train_on_slots(0, False), _train_on_slots(1, False)
    assert not all(th.equal(c[k], d[k]) for k in c)


def test_buffer_mask_marks_inactive_and_revived_slots():
    model = CounterPlay("MlpLstmPolicy", SlotVecEnv(0), counterfactual=False, seed=1, n_steps=16, batch_size=None,
                        n_epochs=1, device="cpu", policy_kwargs=dict(lstm_hidden_size=8, net_arch=[8]))
    model.learn(16 * (2 + 1) - 7)  # learn counts B_post: one generation of live transitions
    buf = model.rollout_buffer
    active = np.asarray(buf.active).reshape(4, 16)  # flattened per env after get()
    assert active[3].sum() == 0 and active[0].all() and active[1].all()
    assert active[2, 5:12].sum() == 0 and active[2, :5].all() and active[2, 12:].all()
    starts = np.asarray(buf.episode_starts).reshape(4, 16)
    # slot 2 comes back at step 12 without a done: its LSTM memory restarts there
    assert starts[2, 12] == 1.0 and starts[0, 12] == 0.0
    assert model.budget.main == 16 * (2 + 1) - 7  # active slot transitions only
    assert model.num_timesteps == model.budget.total == model.budget.main and model.budget.generations == 1


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"panel": ("cautious", "reckless")}, "panel"),
        ({"panel": ()}, "panel"),
        ({"deploy_condition": "sporty"}, "deploy_condition"),
        ({"deploy_condition": [2.0, 99.0, 3, 3, 0.05, 0.015, 0.5, 0.0038, 0.0, 0.0038]}, "deploy_condition"),
        ({"window": (60, 5)}, "window"),
        ({"window": (5, 5)}, "window"),
        ({"rho": 1.2}, "rho"),
        ({"rho": -0.01}, "rho"),
        ({"branch_cap": 0.0}, "branch_cap"),
        ({"branch_cap": -1.0}, "branch_cap"),
        ({"post_budget": 0}, "post_budget"),
        ({"root_interval": 0}, "root_interval"),
        ({"backtrack": "random"}, "backtrack"),
        ({"fixed_depth": 0}, "fixed_depth"),
        ({"selection": "best"}, "selection"),
        ({"distill": "mse"}, "distill"),
        ({"distill_minibatches": 0}, "distill_minibatches"),
        # wrong types name the argument too; a switch is a bool (bool("no") would be True)
        ({"verify": "yes"}, "verify: expected True or False"),
        ({"shared_randomness": 2}, "shared_randomness: expected True or False"),
        ({"rho": "x"}, "rho: expected a number"),
        ({"root_interval": None}, "root_interval: expected a whole number"),
        ({"branch_cap": None}, "branch_cap: expected a number"),
        ({"window": None}, "window: expected a sequence"),
        ({"panel": 5}, "panel: expected a sequence"),
        ({"n_steps": 0}, "n_steps: must be a whole number >= 1"),
        ({"batch_size": -1}, "batch_size: must be a whole number >= 1"),
    ],
)
def test_bad_arguments_raise_value_error_naming_them(kwargs, name):
    env = make_vec_env("CartPole-v1", n_envs=1, seed=0)
    with pytest.raises(ValueError, match=name):
        CounterPlay("MlpLstmPolicy", env, counterfactual=False, **{**SMALL, **kwargs})


def test_counterfactual_must_be_a_bool():
    env = make_vec_env("CartPole-v1", n_envs=1, seed=0)
    with pytest.raises(ValueError, match="counterfactual: expected True or False"):
        CounterPlay("MlpLstmPolicy", env, counterfactual="no", **SMALL)


def test_counterfactual_needs_a_branching_env():
    env = make_vec_env("CartPole-v1", n_envs=1, seed=0)
    with pytest.raises(ValueError, match="env"):
        CounterPlay("MlpLstmPolicy", env, **SMALL)
    with pytest.raises(ValueError, match="env"):
        CounterPlay("MlpLstmPolicy", SlotVecEnv(0), **SMALL)


def test_budget_cap_and_totals():
    b = Budget(branch_cap=0.5)
    b.start_generation()
    b.add_main(1000)
    assert b.generation_allowance == 0  # nothing searched yet: the first generation has no allowance
    b.end_generation()
    # generation 2 runs generation 1's searches against 0.5 x generation 1's main transitions
    b.start_generation()
    b.open_allowance(1000)
    b.add_main(300)
    assert b.generation_allowance == 500 and b.fits(500) and not b.fits(501)
    b.add_branch(factual=100, candidate=250, verification=50)
    assert b.generation_allowance == 100 and not b.fits(101)
    summary = b.end_generation()
    assert summary == {"main": 300, "branch": 400, "cap_main": 1000}
    assert (b.main, b.branch, b.total) == (1300, 400, 1700)
    assert b.branch_share == pytest.approx(400 / 1700)
    b.start_generation()
    b.open_allowance(300)
    assert b.generation_allowance == 150  # a fresh allowance from the searched generation's main steps
    with pytest.raises(ValueError, match="branch_cap"):
        Budget(branch_cap=0)
    with pytest.raises(ValueError, match="post_budget"):
        Budget(post_budget=-5)


def test_budget_allowance_floors_clamps_and_stops_at_post_budget():
    # the cap is a floor of branch_cap x main (never above it): 0.5 x 3 = 1.5 -> 1
    b = Budget(branch_cap=0.5)
    b.open_allowance(3)
    assert b.generation_allowance == 1
    # branch work may overrun an estimate: the allowance is then 0, never negative
    b.open_allowance(1000)
    b.add_branch(candidate=600)
    assert b.generation_allowance == 0 and not b.fits(1) and b.fits(0)
    assert b.remaining is None and not b.exhausted
    # post_budget caps the allowance too: 1000 - 800 main = 200 left < 500 allowed
    b = Budget(branch_cap=0.5, post_budget=1000)
    b.open_allowance(1000)
    b.add_main(799)
    assert b.remaining == 201 and b.generation_allowance == 201 and not b.exhausted
    b.add_main(1)
    assert b.remaining == 200 and b.generation_allowance == 200 and not b.exhausted
    b.add_branch(verification=200)
    assert b.total == 1000 and b.exhausted and b.remaining == 0 and b.generation_allowance == 0
    b.add_main(5)  # a main rollout step may overshoot: nothing is left, not -5
    assert b.remaining == 0 and b.generation_allowance == 0
    assert b.as_dict()["total"] == 1005 and b.as_dict()["branch"] == 200
    with pytest.raises(ValueError, match="post_budget"):
        Budget(post_budget=0)


def test_budget_generation_totals_restart_each_generation():
    b = Budget(branch_cap=1.0)
    b.start_generation()
    b.add_main(100)
    b.open_allowance(100)
    b.add_branch(factual=10, candidate=20)
    assert b.end_generation() == {"main": 100, "branch": 30, "cap_main": 100}
    b.start_generation()
    b.add_main(50)
    b.open_allowance(50)
    b.add_branch(candidate=5)
    assert b.end_generation() == {"main": 50, "branch": 5, "cap_main": 50}
    assert b.history == [{"main": 100, "branch": 30, "cap_main": 100}, {"main": 50, "branch": 5, "cap_main": 50}]
    assert (b.main, b.branch, b.total, b.generations) == (150, 35, 185, 2)


def test_post_budget_stops_learn():
    model = CounterPlay("MlpLstmPolicy", SlotVecEnv(0), counterfactual=False, post_budget=100, seed=0,
                        n_steps=16, batch_size=32, n_epochs=1, device="cpu",
                        policy_kwargs=dict(lstm_hidden_size=8, net_arch=[8]))
    model.learn(10_000)
    # each generation counts 16 steps of active slots (about 40 transitions): the 3rd
    # rollout stops at the step that reaches 100 and is still learned from
    b = model.budget
    assert 100 <= b.total < 100 + model.n_envs
    assert model.num_timesteps < 10_000 and b.generations == 3
    assert b.history[-1]["main"] < b.history[0]["main"]
    assert model.rollout_buffer.buffer_size < 16 and model._n_updates == 3
    # a further learn starts from a full-size buffer again
    model.post_budget = model.budget.post_budget = None
    model.learn(40, reset_num_timesteps=False)
    assert model.rollout_buffer.buffer_size == 16 and model.budget.generations >= 4


def test_save_load_continue(tmp_path):
    env = make_vec_env("CartPole-v1", n_envs=2, seed=5)
    model = CounterPlay("MlpLstmPolicy", env, seed=5, counterfactual=False, rho=0.3, panel=("cautious", "normal"),
                        distill_coef=0.25, **SMALL).learn(128)
    path = tmp_path / "cp.zip"
    model.save(path)
    loaded = CounterPlay.load(path, env=env, device="cpu")
    assert loaded.rho == 0.3 and loaded.panel == ("cautious", "normal") and loaded.distill_coef == 0.25
    assert loaded.counterfactual is False and loaded.budget.main == model.budget.main
    a, b = _params(model), _params(loaded)
    assert all(th.equal(a[k], b[k]) for k in a)
    loaded.learn(128, reset_num_timesteps=False)
    assert loaded.num_timesteps == model.num_timesteps + 128
    assert loaded.budget.main == model.budget.main + 128
    c = _params(loaded)
    assert not all(th.equal(a[k], c[k]) for k in a)
