"""DAgger warm start from the tracking expert (cpalgo.anchor.imitation)."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch as th

import cpsim
from cpalgo.anchor.imitation import ImitationConfig, collect_episodes, imitate_expert, imitation_losses
from cpsim.config import Controller
from cpsim.expert import TrackingExpert

POLICY_KWARGS = dict(lstm_hidden_size=16, enable_critic_lstm=False, net_arch=dict(pi=[16], vf=[16]))


@functools.lru_cache(maxsize=1)
def _pool() -> tuple:
    from cpsim.scenario import train_pool

    return tuple(train_pool(3, 0))


def _model(num_worlds: int = 2):
    from sb3_contrib import RecurrentPPO

    env = cpsim.SelfPlayVecEnv(list(_pool()), num_worlds=num_worlds, max_agents=4, seed=0)
    return RecurrentPPO("MlpLstmPolicy", env, n_steps=8, batch_size=16, seed=0, device="cpu",
                        policy_kwargs=POLICY_KWARGS)


def test_config_rejects_unknown_and_bad_values():
    with pytest.raises(ValueError, match="unknown keys"):
        ImitationConfig.from_dict({"iterations": 1, "rounds": 2})
    with pytest.raises(ValueError, match="beta"):
        ImitationConfig(beta=1.5)
    with pytest.raises(ValueError, match="iterations"):
        ImitationConfig(iterations=0)
    with pytest.raises(ValueError, match="teacher: unknown teacher 'idm'"):
        ImitationConfig(teacher="idm")


def test_expert_driven_episode_is_labelled_with_the_actions_it_took():
    model = _model()
    sim = cpsim.Simulator(list(_pool()), num_worlds=3, max_agents=4, seed=0)
    expert = TrackingExpert(sim)
    batch = collect_episodes(model.policy, sim, expert, beta=1.0, rng=np.random.default_rng(0))
    T, N, D = batch.obs.shape
    assert N == 12 and D == sim.obs_layout.size and batch.mask.any()
    # replay the labels open loop from the same reset: the same world results
    replay = cpsim.Simulator(list(_pool()), num_worlds=3, max_agents=4, seed=0)
    replay.reset(scenario_index=sim.world_scenario.numpy(), conditions=sim.conditions.numpy())
    # masked observations equal the replay's observations at every step
    for t in range(T):
        live = ((replay.controllers == int(Controller.POLICY)) & replay.alive).reshape(-1)
        assert th.equal(live, batch.mask[t])
        obs = replay.obs.reshape(N, -1) * replay.policy_mask.reshape(-1, 1)
        assert th.allclose(obs[live], batch.obs[t][live])
        replay.step(batch.labels[t].reshape(3, 4).to(th.int32))
    # returns are discounted sums of the per-step rewards of live steps: finite, zero when not live
    assert th.isfinite(batch.returns).all()
    assert (batch.returns[~batch.mask] == 0).all()


def test_imitation_loss_falls_on_a_fixed_batch():
    model = _model()
    sim = cpsim.Simulator(list(_pool()), num_worlds=3, max_agents=4, seed=0)
    batch = collect_episodes(model.policy, sim, TrackingExpert(sim), beta=1.0, rng=np.random.default_rng(1))
    opt = th.optim.Adam(model.policy.parameters(), lr=3e-3)
    first = None
    for _ in range(30):
        ce, mse = imitation_losses(model.policy, batch.obs, batch.labels, batch.mask, batch.returns)
        first = (ce.item(), mse.item()) if first is None else first
        opt.zero_grad()
        (ce + mse).backward()
        opt.step()
    ce, mse = imitation_losses(model.policy, batch.obs, batch.labels, batch.mask, batch.returns)
    assert ce.item() < 0.8 * first[0]
    assert mse.item() < first[1]


def test_imitate_expert_trains_the_policy_and_reports_rounds():
    model = _model()
    before = [p.detach().clone() for p in model.policy.parameters()]
    history = imitate_expert(model, config=ImitationConfig(iterations=2, num_worlds=3, epochs=1,
                                                           batch_sequences=8), log=None)
    assert [round(h["beta"], 3) for h in history] == [1.0, 0.5]
    assert all(0.0 <= h["agreement"] <= 1.0 and h["transitions"] > 0 for h in history)
    assert any(not th.equal(a, b) for a, b in zip(before, model.policy.parameters()))
    # the trained model still acts in its env
    obs = model.get_env().reset()
    actions, _ = model.predict(obs, deterministic=True)
    assert actions.shape == (model.get_env().num_envs,)


def test_imitate_the_reactive_teacher():
    model = _model()
    before = [p.detach().clone() for p in model.policy.parameters()]
    history = imitate_expert(model, config=ImitationConfig(iterations=1, num_worlds=3, epochs=1, batch_sequences=8,
                                                           teacher="reactive"), log=None)
    assert history[0]["transitions"] > 0
    assert any(not th.equal(a, b) for a, b in zip(before, model.policy.parameters()))


def test_style_pairs_label_the_same_states_under_swapped_styles():
    from cpsim.conditions import FIELD_INDEX, PANEL, STYLE_MASK, TASK_FIELDS, profile
    from cpsim.expert import ReactiveExpert

    model = _model()
    sim = cpsim.Simulator(list(_pool()), num_worlds=3, max_agents=4, seed=0)
    plain = collect_episodes(model.policy, sim, ReactiveExpert(sim), beta=1.0, rng=np.random.default_rng(2))
    sim = cpsim.Simulator(list(_pool()), num_worlds=3, max_agents=4, seed=0)
    paired = collect_episodes(model.policy, sim, ReactiveExpert(sim), beta=1.0, rng=np.random.default_rng(2),
                              style_pairs=1)
    T, N = plain.labels.shape
    assert paired.obs.shape == (T, 2 * N, plain.obs.shape[-1])
    # the driven half is the plain episode, bit for bit: the swap leaves the world alone
    assert th.equal(paired.obs[:, :N], plain.obs) and th.equal(paired.labels[:, :N], plain.labels)
    assert th.equal(paired.mask[:, N:], plain.mask) and th.equal(paired.value_mask[:, :N], plain.mask)
    assert not paired.value_mask[:, N:].any()
    # the copy differs only in the condition slice, which holds a panel style and the same task
    layout = sim.obs_layout
    live = plain.mask
    other = th.ones(plain.obs.shape[-1], dtype=th.bool)
    other[layout.condition] = False
    assert th.equal(paired.obs[:, N:][live][:, other], plain.obs[live][:, other])
    cond = paired.obs[:, N:][live][:, layout.condition]
    panel = th.as_tensor(np.stack([cpsim.normalize_condition(profile(p)) for p in PANEL]))[:, th.as_tensor(STYLE_MASK)]
    style = cond[:, th.as_tensor(STYLE_MASK)]
    assert th.isclose(style[:, None, :], panel[None].float(), atol=1e-5).all(-1).any(-1).all()
    task = [FIELD_INDEX[f] for f in TASK_FIELDS]
    assert th.allclose(cond[:, task], plain.obs[live][:, layout.condition][:, task])
    # and the teacher's labels under the swapped styles differ somewhere
    assert (paired.labels[:, N:][live] != plain.labels[live]).any()
    # imitate_expert trains on both halves
    model = _model()
    history = imitate_expert(model, config=ImitationConfig(iterations=1, num_worlds=3, epochs=1, batch_sequences=8,
                                                           teacher="reactive", style_pairs=1), log=None)
    single = imitate_expert(_model(), config=ImitationConfig(iterations=1, num_worlds=3, epochs=1, batch_sequences=8,
                                                             teacher="reactive"), log=None)
    # the round counts the driven transitions, not the labelled copies
    assert history[0]["transitions"] == single[0]["transitions"] > 0
    with pytest.raises(ValueError, match="style_pairs"):
        ImitationConfig(style_pairs=-1)
    with pytest.raises(ValueError, match="tracking teacher ignores the style"):
        ImitationConfig(style_pairs=1, teacher="tracking")
    # returns are repeated, but the critic sees the driven copy only
    assert th.equal(paired.returns[:, N:], plain.returns)
    ce, mse = imitation_losses(model.policy, paired.obs, paired.labels, paired.mask, paired.returns,
                               th.zeros_like(paired.mask))
    assert mse.item() == 0.0 and ce.item() > 0.0


def test_imitate_expert_rejects_a_mismatched_observation_space():
    model = _model()
    with pytest.raises(ValueError, match="observation shape"):
        imitate_expert(model, sim_config={"num_partners": 4}, config=ImitationConfig(iterations=1, num_worlds=2),
                       log=None)
