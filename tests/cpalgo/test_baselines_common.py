"""Shared machinery of the adapted baselines (cpalgo.common.hooked_train / continuations):
interaction triggers, root sampling, the continuation runner's budget and returns, and
argument validation of all six methods. Tiny settings: 2 worlds x 4 slots, LSTM 16.

The helpers at the top are imported by the other ``test_baselines_*`` files."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from cpalgo.baselines.continuations import (  # noqa: E402
    ContinuationRunner,
    GroupJob,
    RootReservoir,
    branch_simulator_factory,
    group_normalized,
    interaction_trigger,
    neutral_action,
)
from cpalgo.methods import build_method  # noqa: E402
from cpalgo.methods.base import BudgetedCounterPlay, base_vec_env  # noqa: E402
from cpsim import SelfPlayVecEnv  # noqa: E402

EPISODE = 40
POLICY = dict(lstm_hidden_size=16, enable_critic_lstm=False, net_arch=[32])
ALGO = dict(n_steps=EPISODE, batch_size=64, n_epochs=1, policy_kwargs=POLICY)
#: every live agent within 50 m of another triggers; a wide allowance so groups run on tiny rollouts
GROUPS = dict(branch_cap=8.0, trigger="distance", trigger_distance=50.0)
#: SPICED's reference, cloned from a handful of expert episodes
TINY_REFERENCE = dict(reference_worlds=2, reference_episodes=1, reference_epochs=2, reference_hidden=16)
CONTINUATION_METHODS = ("dapo", "vineppo", "plannerrft", "craft")
ALL_METHODS = ("spiced", "cl4ad", *CONTINUATION_METHODS)


def tiny_settings(name: str) -> dict:
    """The settings every test gives method ``name`` (tiny reference, groups that run)."""
    if name == "spiced":
        return dict(TINY_REFERENCE)
    if name in CONTINUATION_METHODS:
        return dict(GROUPS)
    return {}


def make_env(seed: int = 0) -> SelfPlayVecEnv:
    return SelfPlayVecEnv(num_worlds=2, max_agents=4, num_scenarios=4, seed=seed, episode_steps=EPISODE)


def save_anchor(path) -> str:
    BudgetedCounterPlay("MlpLstmPolicy", make_env(), counterfactual=False, seed=0, **ALGO).save(path)
    return str(path)


def build(name: str, anchor: str, **settings):
    return build_method(name, anchor, make_env(), algo_kwargs=ALGO, settings={**tiny_settings(name), **settings},
                        seed=0)


def collect(model) -> None:
    """One rollout (``n_steps`` decisions) as ``learn`` would run it, without the update."""
    _, callback = model._setup_learn(10**9, None)
    callback.on_training_start(locals(), globals())
    assert model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)


pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def anchor(tmp_path_factory) -> str:
    return save_anchor(tmp_path_factory.mktemp("anchor") / "anchor.zip")


# ----------------------------------------------------------------------------- pure pieces
def test_interaction_trigger_distance_and_time_to_collision():
    # world 0: agents 0 and 1 head-on, 20 m apart, closing at 10 m/s (TTC 2 s); agent 2 far away
    xy = np.array([[[0, 0], [20, 0], [500, 0]]], np.float32)
    vel = np.array([[[5, 0], [-5, 0], [0, 0]]], np.float32)
    alive = np.ones((1, 3), bool)
    cand = np.ones((1, 3), bool)
    assert interaction_trigger(xy, vel, alive, cand, "ttc", ttc=3.0).tolist() == [[True, True, False]]
    assert not interaction_trigger(xy, vel, alive, cand, "ttc", ttc=1.5).any()
    assert interaction_trigger(xy, vel, alive, cand, "distance", distance=25.0).tolist() == [[True, True, False]]
    assert not interaction_trigger(xy, vel, alive, cand, "distance", distance=10.0).any()
    # moving apart: no time to collision however close
    assert not interaction_trigger(xy, -vel, alive, cand, "ttc", ttc=100.0).any()
    # a removed partner is nobody to meet; a non-candidate never triggers
    dead = alive.copy()
    dead[0, 1] = False
    assert not interaction_trigger(xy, vel, dead, cand, "either", distance=25.0, ttc=3.0)[0, 0]
    only0 = np.array([[True, False, False]])
    assert interaction_trigger(xy, vel, alive, only0, "ttc").tolist() == [[True, False, False]]
    with pytest.raises(ValueError, match="trigger"):
        interaction_trigger(xy, vel, alive, cand, "sometimes")


def test_root_reservoir_is_a_uniform_sample_of_everything_offered():
    counts = np.zeros(20)
    for seed in range(400):
        res = RootReservoir(5, np.random.default_rng(seed))
        for item in range(20):
            (slot,) = res.slots_for(1)
            if slot >= 0:
                res.put(slot, item)
        assert len(res.roots) == 5 and res.offered == 20
        counts[res.roots] += 1
    share = counts / 400
    assert np.allclose(share, 5 / 20, atol=0.08)  # each item kept with probability 1/4


def test_group_normalized_and_neutral_actions():
    adv = group_normalized(np.array([[1.0, 2.0, 3.0], [5.0, 5.0, 5.0]]))
    assert adv[0].mean() == pytest.approx(0.0, abs=1e-6) and adv[0].std() == pytest.approx(1.0, abs=1e-4)
    assert np.all(adv[1] == 0.0)
    assert neutral_action("jerk") == 7 and neutral_action("classic") == 45


# ----------------------------------------------------------------------------- runner
def test_continuations_count_every_agent_step_and_return_discounted_focal_rewards(anchor):
    model = build("dapo", anchor)
    collect(model)
    roots, results = model.last_groups
    assert roots, "the distance trigger finds roots on every rollout"
    b = model.budget
    assert b.candidate == sum(int(r.transitions.sum()) for r in results) > 0
    assert model.num_timesteps == b.total  # B_post counts the continuations
    assert b.candidate <= b.branch_cap * b.allowance_main  # never over the generation's allowance
    for root, res in zip(roots, results):
        assert res.transitions.shape == (model.group_size,)
        # a continuation ends with its focal task, at the latest at the original deadline
        assert np.all(res.length <= root.horizon) and np.all(res.length >= 1)
        # transitions: every agent that was deciding at the root, while it lives and the world runs
        assert np.all(res.transitions <= res.length * root.deciding.sum())
        assert np.all(res.transitions >= res.length)
        for j in range(model.group_size):
            n = int(res.length[j])
            assert res.alive[j, :n].all() and not res.alive[j, n:].any()
            rewards = res.rewards[j, :n].numpy().astype(np.float64)
            expected = float((rewards * model.gamma ** np.arange(n)).sum())
            if res.outcome[j] == 4:  # cut at the deadline: the critic bootstraps the rest
                assert res.length[j] == root.horizon
                assert res.returns[j] != pytest.approx(expected, abs=1e-7) or rewards.size == 0
            else:
                assert res.returns[j] == pytest.approx(expected, rel=1e-5, abs=1e-6)
            # the behaviour log-probs are the policy's (temperature 1 here)
            assert np.all(res.logp_old[j, :n].numpy() <= 0.0)


def test_runner_replays_a_root_deterministically_with_the_same_draws(anchor):
    model = build("dapo", anchor)
    collect(model)
    root = model.last_groups[0][0]
    sim = base_vec_env(model.env).sim
    out = []
    for _ in range(2):
        runner = ContinuationRunner(branch_simulator_factory(sim), model.policy, model.gamma,
                                    th.Generator().manual_seed(3))
        out.append(runner.run([GroupJob(root=root, traffic=["policy"] * 3)])[0])
    assert np.array_equal(out[0].coplayer_actions, out[1].coplayer_actions)
    assert np.array_equal(out[0].returns, out[1].returns)
    # the root's world as restored: every continuation starts from the same positions
    assert np.array_equal(out[0].xy[:, 0], np.repeat(out[0].xy[:1, 0], 3, 0))
    # independent focal draws: the continuations of a group differ
    assert not all(np.array_equal(out[0].actions[0], out[0].actions[j]) for j in (1, 2))


def test_continuation_rewards_are_clamped_as_the_rollouts_are(anchor):
    """With ``clip_reward`` the continuations' rewards and returns (VinePPO's values, DAPO's and
    PlannerRFT's advantages, CRAFT's residuals) use the learner's clamped reward."""
    c = 0.01
    model = build("dapo", anchor, clip_reward=c)
    collect(model)
    assert model._runner.clip_reward == c
    root = model.last_groups[0][0]
    sim = base_vec_env(model.env).sim
    out = {}
    for clip in (None, c):
        runner = ContinuationRunner(branch_simulator_factory(sim), model.policy, model.gamma,
                                    th.Generator().manual_seed(3), clip_reward=clip)
        out[clip] = runner.run([GroupJob(root=root, traffic=["policy"] * 3)])[0]
    raw, clamped = out[None], out[c]
    assert np.array_equal(raw.actions.numpy(), clamped.actions.numpy())  # the same draws, the same drive
    assert (raw.rewards.abs() > c).any()
    assert th.equal(clamped.rewards, raw.rewards.clamp(-c, c))
    for j in range(3):
        if clamped.outcome[j] != 4:  # not cut at the deadline: the discounted sum of the clamped rewards
            n = int(clamped.length[j])
            expected = float((clamped.rewards[j, :n].numpy() * model.gamma ** np.arange(n)).sum())
            assert clamped.returns[j] == pytest.approx(expected, rel=1e-5, abs=1e-6)


# ----------------------------------------------------------------------------- validation
@pytest.mark.parametrize("name, setting, value", [
    ("spiced", "kl_coef", -0.1), ("spiced", "kl_direction", "sideways"), ("spiced", "reference_epochs", 0),
    ("cl4ad", "curriculum_temperature", 0.0), ("cl4ad", "curriculum_uniform", 1.5), ("cl4ad", "success_decay", 0.0),
    ("dapo", "clip_low", 1.0), ("dapo", "clip_high", 0.0), ("dapo", "group_size", 1), ("dapo", "trigger", "sometimes"),
    ("dapo", "trigger_ttc", 0.0), ("vineppo", "min_horizon", 0), ("vineppo", "root_pool", 0),
    ("plannerrft", "temperature_min", 1.5), ("plannerrft", "temperature_max", 0.9), ("plannerrft", "head_epochs", 0),
    ("craft", "proxy_decay", 1.0), ("craft", "proxy_hold", -1), ("craft", "residual_rollouts", 4),
    ("craft", "ema_decay", 1.2), ("craft", "kl_forward_coef", -1.0),
])
def test_bad_settings_raise_value_errors_naming_the_argument(anchor, name, setting, value):
    with pytest.raises(ValueError, match=f"^{setting}:"):
        build(name, anchor, **{setting: value})


def test_the_baselines_refuse_the_counterplay_search(anchor):
    for name in ALL_METHODS:
        with pytest.raises(ValueError, match="^counterfactual:"):
            build(name, anchor, counterfactual=True)
