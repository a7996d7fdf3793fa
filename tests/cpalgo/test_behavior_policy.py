"""BehaviorBench's network shape (cpalgo.policies.behavior) and the learner options of the
anchor recipe (reward clamp, one schedule over several learn calls)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from sb3_contrib import RecurrentPPO
from sb3_contrib.common.recurrent.type_aliases import RNNStates

from cpalgo.counterplay.algorithm import CounterPlay
from cpalgo.policies import BehaviorEncoder, BehaviorLstmPolicy
from cpalgo.recipes import CosineSchedule
from cpsim import SelfPlayVecEnv
from cpsim.observation import ObsLayout

LAYOUT = ObsLayout()
SPACE = gym.spaces.Box(-1.0, 1.0, (LAYOUT.size,), np.float32)


def _obs(n: int, seed: int = 0) -> th.Tensor:
    return th.as_tensor(np.random.default_rng(seed).uniform(-1, 1, (n, LAYOUT.size)), dtype=th.float32)


def test_encoder_pools_partners_and_road_over_their_slots():
    th.manual_seed(0)
    enc = BehaviorEncoder(SPACE)
    x = _obs(5)
    y = enc(x)
    assert y.shape == (5, 128) and (y >= 0).all()  # ReLU output
    # max-pooling: the order of partner and road slots does not matter ...
    perm = x.clone()
    parts = LAYOUT.split(perm)
    parts["partners"][:] = parts["partners"][:, th.randperm(LAYOUT.num_partners)]
    parts["road"][:] = parts["road"][:, th.randperm(LAYOUT.num_road)]
    th.testing.assert_close(enc(perm), y, rtol=1e-5, atol=1e-6)
    # ... but what is in them does, and so do the ego and condition groups
    for group in ("partners", "road", "ego", "condition"):
        other = x.clone()
        LAYOUT.split(other)[group][:] = 0.0
        assert not th.allclose(enc(other), y), group


def test_encoder_names_a_layout_mismatch():
    with pytest.raises(ValueError, match="num_partners=8"):
        BehaviorEncoder(SPACE, num_partners=8)
    with pytest.raises(ValueError, match="road_width"):
        BehaviorEncoder(SPACE, road_width=0)
    small = ObsLayout(num_partners=4, num_road=8)
    enc = BehaviorEncoder(gym.spaces.Box(-1, 1, (small.size,)), num_partners=4, num_road=8)
    assert enc(th.zeros(2, small.size)).shape == (2, 128)


def _policy(**kwargs) -> BehaviorLstmPolicy:
    return BehaviorLstmPolicy(SPACE, gym.spaces.Discrete(91), lambda _: 1e-3, **kwargs)


def test_critic_trains_the_shared_lstm_and_encoder():
    """sb3-contrib's shared_lstm detaches the critic; here the value loss reaches the LSTM
    and the branches, and actor and critic read one LSTM state."""
    th.manual_seed(0)
    policy = _policy()
    assert policy.lstm_critic is None and policy.shared_lstm
    n = 6
    zeros = th.zeros(1, n, 128)
    states = RNNStates((zeros, zeros), (zeros, zeros))
    values, _, _ = policy.evaluate_actions(_obs(n), th.zeros(n), states, th.ones(n))
    policy.zero_grad()
    values.sum().backward()
    assert policy.lstm_actor.weight_ih_l0.grad.abs().sum() > 0
    assert policy.features_extractor.road[0].weight.grad.abs().sum() > 0
    assert policy.action_net.weight.grad is None or policy.action_net.weight.grad.abs().sum() == 0
    with th.no_grad():
        _, v_fwd, _, out = policy(_obs(n), states, th.ones(n))
        v_eval, _, _ = policy.evaluate_actions(_obs(n), th.zeros(n), states, th.ones(n))
        v_pred = policy.predict_values(_obs(n), states.vf, th.ones(n))
    th.testing.assert_close(v_fwd, v_eval)
    th.testing.assert_close(v_fwd, v_pred)
    assert out.pi[0] is out.vf[0]
    with pytest.raises(ValueError, match="shared_lstm"):
        _policy(shared_lstm=False)


@pytest.fixture(scope="module")
def env():
    return SelfPlayVecEnv(num_worlds=2, max_agents=4, seed=0, dynamics="classic", num_scenarios=4)


def test_plain_recurrent_ppo_and_counterplay_accept_it(env):
    ppo = RecurrentPPO(BehaviorLstmPolicy, env, n_steps=8, batch_size=32, n_epochs=1, seed=0)
    before = [p.detach().clone() for p in ppo.policy.parameters()]
    ppo.learn(8 * env.num_envs)
    assert any(not th.equal(a, b) for a, b in zip(before, ppo.policy.parameters()))
    cp = CounterPlay("BehaviorLstmPolicy", env, counterfactual=False, n_steps=8, batch_size=32, n_epochs=1, seed=0)
    assert isinstance(cp.policy, BehaviorLstmPolicy)
    assert cp.policy.features_extractor.layout == env.obs_layout
    cp.learn(1)
    assert cp.num_timesteps > 0


def test_clip_reward_clamps_what_enters_the_buffer(env):
    seen = []

    class Spy(CounterPlay):
        def _bootstrap_timeouts(self, rewards, dones, infos, lstm_states):
            seen.append(rewards.copy())
            super()._bootstrap_timeouts(rewards, dones, infos, lstm_states)

    raw = Spy("BehaviorLstmPolicy", env, counterfactual=False, n_steps=32, batch_size=64, n_epochs=1, seed=0)
    raw.learn(1)
    big = float(np.abs(np.concatenate(seen)).max())
    assert big > 1e-3
    seen.clear()
    cap = big / 4
    clipped = Spy("BehaviorLstmPolicy", env, counterfactual=False, n_steps=32, batch_size=64, n_epochs=1,
                  seed=0, clip_reward=cap)
    clipped.learn(1)
    assert float(np.abs(np.concatenate(seen)).max()) == pytest.approx(cap)
    with pytest.raises(ValueError, match="clip_reward"):
        CounterPlay("BehaviorLstmPolicy", env, counterfactual=False, clip_reward=0.0)


def test_schedule_runs_over_the_whole_run_across_learn_calls(env):
    model = CounterPlay("BehaviorLstmPolicy", env, counterfactual=False, n_steps=8, batch_size=32, n_epochs=1,
                        seed=0, learning_rate=CosineSchedule(1e-3), schedule_timesteps=10_000)
    model.learn(1)
    model.learn(1, reset_num_timesteps=False)
    progress = 1.0 - model.num_timesteps / 10_000
    assert model._current_progress_remaining == pytest.approx(progress)
    assert progress > 0.9  # SB3's own rule would put the second call's end at progress 0
    lr = model.policy.optimizer.param_groups[0]["lr"]
    assert lr == pytest.approx(CosineSchedule(1e-3)(progress))
    with pytest.raises(ValueError, match="schedule_timesteps"):
        CounterPlay("BehaviorLstmPolicy", env, counterfactual=False, schedule_timesteps=0)


def test_training_pass_encodes_only_counted_rows():
    """In a minibatch of padded sequences the encoder sees only the counted rows; values,
    log-probs and gradients on those rows equal the pass over every row."""
    from cpalgo.policies import sequence_lengths

    th.manual_seed(0)
    policy = _policy(lstm_hidden_size=16)
    n_seq, seq_len = 3, 5
    lengths = th.tensor([5, 2, 3])
    mask = (th.arange(seq_len)[None, :] < lengths[:, None]).reshape(-1)
    obs, actions = _obs(n_seq * seq_len, seed=1), th.randint(0, 91, (n_seq * seq_len,))
    zeros = th.zeros(1, n_seq, 16)
    states = RNNStates((zeros, zeros), (zeros, zeros))
    starts = th.zeros(n_seq * seq_len)
    seen = []
    policy.features_extractor.register_forward_hook(lambda mod, inp, out: seen.append(inp[0].shape[0]))
    full = policy.evaluate_actions(obs, actions, states, starts)
    with sequence_lengths(policy, mask, n_seq):
        part = policy.evaluate_actions(obs, actions, states, starts)
    assert seen == [n_seq * seq_len, int(mask.sum())]
    for a, b in zip(full, part):
        th.testing.assert_close(a.flatten()[mask], b.flatten()[mask])
    grads = []
    for out in (full, part):
        policy.zero_grad()
        (out[0].flatten()[mask].sum() + out[1][mask].sum()).backward(retain_graph=True)
        grads.append([p.grad.clone() for p in policy.parameters() if p.grad is not None])
    for a, b in zip(*grads):
        th.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
