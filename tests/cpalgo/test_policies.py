"""The fused-sequence LSTM policies and active-only minibatches."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from sb3_contrib import RecurrentPPO
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from stable_baselines3.common.env_util import make_vec_env

from cpalgo import CounterPlay
from cpalgo.common.buffers import MaskedRecurrentRolloutBuffer
from cpalgo.policies import MlpLstmPolicy, fused_process_sequence, lengths_from_mask, sequence_lengths

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def _pair(enable_critic_lstm: bool, seed: int = 0) -> tuple[RecurrentActorCriticPolicy, MlpLstmPolicy]:
    obs_space = spaces.Box(-1, 1, (7,), np.float32)
    kwargs = dict(lstm_hidden_size=12, net_arch=dict(pi=[16], vf=[16]), enable_critic_lstm=enable_critic_lstm)
    th.manual_seed(seed)
    stock = RecurrentActorCriticPolicy(obs_space, spaces.Discrete(5), lambda _: 1e-3, **kwargs)
    fused = MlpLstmPolicy(obs_space, spaces.Discrete(5), lambda _: 1e-3, **kwargs)
    fused.load_state_dict(stock.state_dict())
    return stock, fused


def _sequences(n_seq: int, seq_len: int, inside: bool, seed: int = 1):
    g = th.Generator().manual_seed(seed)
    obs = th.rand(n_seq * seq_len, 7, generator=g) * 2 - 1
    starts = th.zeros(n_seq, seq_len)
    starts[::2, 0] = 1.0  # every other sequence starts an episode at its first element
    if inside:
        starts[1, seq_len // 2] = 1.0
    h = th.randn(1, n_seq, 12, generator=g)
    c = th.randn(1, n_seq, 12, generator=g)
    return obs, starts.reshape(-1), h, c


@pytest.mark.parametrize("enable_critic_lstm", [False, True])
@pytest.mark.parametrize("inside", [False, True])
def test_fused_policy_equals_stock_logits_and_values(enable_critic_lstm: bool, inside: bool):
    stock, fused = _pair(enable_critic_lstm)
    obs, starts, h, c = _sequences(n_seq=6, seq_len=9, inside=inside)
    actions = th.randint(0, 5, (obs.shape[0],), generator=th.Generator().manual_seed(2))
    from sb3_contrib.common.recurrent.type_aliases import RNNStates

    states = RNNStates((h, c), (h.flip(1), c.flip(1)))
    v_s, lp_s, ent_s = stock.evaluate_actions(obs, actions, states, starts)
    v_f, lp_f, ent_f = fused.evaluate_actions(obs, actions, states, starts)
    assert th.allclose(v_s, v_f, atol=1e-5) and th.allclose(lp_s, lp_f, atol=1e-5)
    assert th.allclose(ent_s, ent_f, atol=1e-5)
    logits_s = stock.get_distribution(obs, states.pi, starts)[0].distribution.logits.clone()
    logits_f = fused.get_distribution(obs, states.pi, starts)[0].distribution.logits.clone()
    assert th.allclose(logits_s, logits_f, atol=1e-5)
    # the memory really was used: zeroing it changes the outputs of non-starting sequences
    zero = RNNStates((th.zeros_like(h), th.zeros_like(c)), (th.zeros_like(h), th.zeros_like(c)))
    assert not th.allclose(fused.evaluate_actions(obs, actions, zero, starts)[1], lp_f, atol=1e-4)


def test_fused_path_runs_one_lstm_call_and_steps_only_with_inner_starts():
    lstm = th.nn.LSTM(7, 12)
    calls = []
    lstm.register_forward_hook(lambda *_: calls.append(1))
    obs, starts, h, c = _sequences(n_seq=4, seq_len=8, inside=False)
    fused_process_sequence(obs, (h, c), starts, lstm)
    assert len(calls) == 1
    calls.clear()
    obs, starts, h, c = _sequences(n_seq=4, seq_len=8, inside=True)
    fused_process_sequence(obs, (h, c), starts, lstm)
    assert len(calls) == 8  # stepping fallback


def test_lengths_from_mask_cuts_only_trailing_zeros():
    mask = th.tensor([[1, 1, 0, 0], [1, 0, 1, 0], [0, 0, 0, 0], [1, 1, 1, 1]], dtype=th.float32).reshape(-1)
    assert lengths_from_mask(mask, 4).tolist() == [2, 3, 1, 4]


@pytest.mark.parametrize("enable_critic_lstm", [False, True])
def test_length_buckets_equal_padded_on_counted_rows_and_gradients(enable_critic_lstm: bool):
    _, fused = _pair(enable_critic_lstm)
    n_seq, seq_len = 6, 9
    obs, starts, h, c = _sequences(n_seq=n_seq, seq_len=seq_len, inside=False)
    lengths = th.tensor([9, 3, 1, 7, 5, 2])
    mask = (th.arange(seq_len)[None, :] < lengths[:, None]).float().reshape(-1)
    # a zero inside a sequence (an inactive step) is not padding: the memory crosses it
    mask[1 * seq_len + 1] = 0.0
    obs = obs * mask[:, None].clamp(min=0.5)  # padding rows differ from real ones
    actions = th.randint(0, 5, (obs.shape[0],), generator=th.Generator().manual_seed(2))
    from sb3_contrib.common.recurrent.type_aliases import RNNStates

    states = RNNStates((h, c), (h.flip(1), c.flip(1)))
    calls: list[object] = []
    fused.lstm_actor.register_forward_hook(lambda _m, args, _o: calls.append(args[0]))

    def loss_and_grads(bucketed: bool):
        fused.zero_grad()
        if bucketed:
            with sequence_lengths(fused, mask, n_seq):
                out = fused.evaluate_actions(obs, actions, states, starts)
        else:
            out = fused.evaluate_actions(obs, actions, states, starts)
        keep = mask > 0
        loss = (out[0].flatten()[keep] ** 2).mean() - out[1][keep].mean() - out[2][keep].mean()
        loss.backward()
        return out, {k: p.grad.clone() for k, p in fused.named_parameters() if p.grad is not None}

    (v_pad, lp_pad, ent_pad), g_pad = loss_and_grads(False)
    (v_pk, lp_pk, ent_pk), g_pk = loss_and_grads(True)
    real = mask > 0
    assert th.allclose(v_pad.flatten()[real], v_pk.flatten()[real], atol=1e-5)
    assert th.allclose(lp_pad[real], lp_pk[real], atol=1e-5)
    assert th.allclose(ent_pad[real], ent_pk[real], atol=1e-5)
    assert g_pad.keys() == g_pk.keys() and all(th.allclose(g_pad[k], g_pk[k], atol=1e-5) for k in g_pad)
    # the bucketed calls skipped padding (quarters of 9 steps: lengths 1-3, 5, 7, 9), and
    # the hint does not outlive the block
    bucket_calls = calls[-4:]  # the hook sits on the actor LSTM only
    assert sorted(int(x.shape[0]) * int(x.shape[1]) for x in bucket_calls) == sorted([3 * 3, 5 * 1, 7 * 1, 9 * 1])
    assert fused._sequence_lengths is None


def test_recurrent_ppo_accepts_the_fused_policy_and_learns_the_same():
    kw = dict(n_steps=32, batch_size=32, n_epochs=2, seed=5, device="cpu",
              policy_kwargs=dict(lstm_hidden_size=16, net_arch=[16]))
    stock = RecurrentPPO("MlpLstmPolicy", make_vec_env("CartPole-v1", n_envs=2, seed=5), **kw).learn(128)
    fused = RecurrentPPO(MlpLstmPolicy, make_vec_env("CartPole-v1", n_envs=2, seed=5), **kw).learn(128)
    a, b = stock.policy.state_dict(), fused.policy.state_dict()
    assert all(th.allclose(a[k], b[k], atol=1e-5) for k in a)
    assert CounterPlay.policy_aliases["MlpLstmPolicy"] is MlpLstmPolicy


# ---------------------------------------------------------------------- active-only minibatches
def _filled_buffer(n_live: int, n_dead: int, dead_gap: bool, seed: int = 0) -> MaskedRecurrentRolloutBuffer:
    """A buffer of ``n_live`` live envs (identical data whatever ``n_dead``) followed by
    ``n_dead`` never-active envs holding garbage. With ``dead_gap``, live env 1 is inactive
    for steps 3..5 and restarts an episode at 6."""
    T, n = 10, n_live + n_dead
    buf = MaskedRecurrentRolloutBuffer(T, spaces.Box(-1, 1, (7,), np.float32), spaces.Discrete(5),
                                       (T, 1, n, 12), "cpu", n_envs=n)
    buf.active_only = True
    live = np.random.default_rng(seed)
    garbage = np.random.default_rng(100 + n_dead)
    for t in range(T):
        obs = np.concatenate([live.uniform(-1, 1, (n_live, 7)), garbage.normal(size=(n_dead, 7)) * 9]).astype(np.float32)
        reward = np.concatenate([live.normal(size=n_live), garbage.normal(size=n_dead) * 9]).astype(np.float32)
        starts = np.zeros(n, np.float32)
        starts[0] = float(t == 4)
        active = np.r_[np.ones(n_live, bool), np.zeros(n_dead, bool)]
        if dead_gap:
            active[1] = not 3 <= t <= 5
            starts[1] = float(t == 6)
        states = tuple(th.as_tensor(live.normal(size=(1, n_live, 12)), dtype=th.float32) for _ in range(4))
        states = tuple(th.cat([s, th.as_tensor(garbage.normal(size=(1, n_dead, 12)), dtype=th.float32)], 1) for s in states)
        from sb3_contrib.common.recurrent.type_aliases import RNNStates

        actions = np.r_[live.integers(0, 5, n_live), garbage.integers(0, 5, n_dead)][:, None]
        buf.add(obs, actions, reward, starts,
                th.as_tensor(np.r_[live.normal(size=n_live), garbage.normal(size=n_dead)], dtype=th.float32),
                th.as_tensor(np.r_[live.normal(size=n_live), garbage.normal(size=n_dead)], dtype=th.float32),
                lstm_states=RNNStates(states[:2], states[2:]), active=active)
    buf.compute_returns_and_advantage(th.zeros(n), np.zeros(n))
    return buf


def _loss(policy: MlpLstmPolicy, buf: MaskedRecurrentRolloutBuffer) -> tuple[float, int]:
    """CounterPlay's masked PPO + value + entropy loss on one full-buffer minibatch."""
    np.random.seed(0)
    (data,) = list(buf.get(None))
    mask = data.mask > 1e-8
    values, log_prob, entropy = policy.evaluate_actions(data.observations, data.actions.long().flatten(),
                                                        data.lstm_states, data.episode_starts)
    adv = data.advantages
    adv = (adv - adv[mask].mean()) / (adv[mask].std() + 1e-8)
    ratio = th.exp(log_prob - data.old_log_prob)
    pg = -th.mean(th.min(adv * ratio, adv * th.clamp(ratio, 0.8, 1.2))[mask])
    vf = th.mean(((data.returns - values.flatten()) ** 2)[mask])
    return float((pg + 0.5 * vf - 0.01 * th.mean(entropy[mask])).detach()), int(data.observations.shape[0])


@pytest.mark.parametrize("dead_gap", [False, True])
def test_dead_slots_change_neither_the_loss_nor_the_compute(dead_gap: bool):
    _, policy = _pair(False)
    base_loss, base_rows = _loss(policy, _filled_buffer(4, 0, dead_gap))
    dead_loss, dead_rows = _loss(policy, _filled_buffer(4, 5, dead_gap))
    assert dead_rows == base_rows  # the dead envs' transitions never reach the network
    assert abs(dead_loss - base_loss) < 1e-5


def test_active_only_sequences_restart_after_gaps_and_keep_every_active_transition():
    buf = _filled_buffer(3, 2, dead_gap=True)
    np.random.seed(3)
    batches = list(buf.get(7))
    total = sum(int((b.mask > 0).sum()) for b in batches)
    assert total == 3 * 10 - 3  # 30 live transitions minus the gap of env 1
    assert buf.num_minibatches(7) == len(batches) == -(-27 // 7)
    # every padded sequence starts at a sequence boundary: no sequence spans env 1's gap
    for b in batches:
        m = (b.mask > 0).reshape(b.lstm_states.pi[0].shape[1], -1)
        lengths = m.sum(1)
        assert bool((m[:, 0]).all()) and int(lengths.max()) <= 10


@pytest.mark.cuda
@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")
def test_fused_policy_on_cuda_equals_the_cpu_result():
    stock, fused = _pair(enable_critic_lstm=True)
    obs, starts, h, c = _sequences(n_seq=6, seq_len=9, inside=False)
    from sb3_contrib.common.recurrent.type_aliases import RNNStates

    states = RNNStates((h, c), (h, c))
    cpu_values = fused.evaluate_actions(obs, th.zeros(obs.shape[0], dtype=th.long), states, starts)[0]
    fused = fused.to("cuda")
    to = lambda x: x.to("cuda")  # noqa: E731
    gpu_states = RNNStates((to(h), to(c)), (to(h), to(c)))
    gpu_values = fused.evaluate_actions(to(obs), th.zeros(obs.shape[0], dtype=th.long, device="cuda"),
                                        gpu_states, to(starts))[0]
    assert th.allclose(cpu_values, gpu_values.cpu(), atol=1e-4)
