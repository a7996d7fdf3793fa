"""Distillation term: KL(teacher || student) and the PPO ablation, on a real LSTM policy."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from sb3_contrib.ppo_recurrent.policies import MlpLstmPolicy

from cpalgo.common.policy_utils import actor_logits
from cpalgo.counterplay.distill import Teacher, collate_teachers, distill_loss, kl_loss, ppo_loss
from cpsim.conditions import STYLE_MASK, normalize_condition, profile

OBS_DIM = 16
COND = slice(3, 13)  # where the fake layout keeps the normalised condition


pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def replace_condition(obs: th.Tensor, raw: th.Tensor) -> th.Tensor:
    out = obs.clone()
    out[..., COND] = normalize_condition(raw)
    return out


def make_policy(seed: int = 0) -> MlpLstmPolicy:
    th.manual_seed(seed)
    return MlpLstmPolicy(
        spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32), spaces.Discrete(5), lambda _: 1e-2,
        lstm_hidden_size=8, net_arch=[16],
    )


def make_teachers(policy, lengths, seed=0, own_logits=False, w_dep=None):
    gen = th.Generator().manual_seed(seed)
    teachers = []
    layers, hidden = policy.lstm_actor.num_layers, policy.lstm_actor.hidden_size
    for n in lengths:
        obs = th.randn(n, OBS_DIM, generator=gen)
        cond = profile("cautious")
        obs = replace_condition(obs, th.as_tensor(cond))
        pi = (th.randn(layers, hidden, generator=gen) * 0.3, th.randn(layers, hidden, generator=gen) * 0.3)
        vf = (th.zeros(layers, hidden), th.zeros(layers, hidden))
        if own_logits:
            # the student's own view of this trajectory: teacher and student coincide
            student_cond = np.where(STYLE_MASK, w_dep, cond)
            sobs = replace_condition(obs, th.as_tensor(student_cond))
            with th.no_grad():
                logits, _ = actor_logits(policy, sobs, (pi[0][:, None].contiguous(), pi[1][:, None].contiguous()),
                                         th.zeros(n))
        else:
            logits = th.randn(n, 5, generator=gen) * 2.0
        teachers.append(Teacher(obs=obs, logits=logits, actions=th.randint(0, 5, (n,), generator=gen),
                                rewards=th.randn(n, generator=gen), pi_state=pi, vf_state=vf, condition=cond,
                                profile="cautious"))
    return teachers


def test_kl_is_zero_when_teacher_and_student_coincide():
    policy = make_policy()
    w_dep = profile("normal")
    teachers = make_teachers(policy, [7, 3, 11], own_logits=True, w_dep=w_dep)
    batch = collate_teachers(teachers, w_dep, replace_condition, STYLE_MASK)
    assert batch.student_obs.shape == (3 * 11, OBS_DIM)
    assert float(kl_loss(policy, batch).detach()) == pytest.approx(0.0, abs=1e-7)
    # the same teachers judged under another deployment condition are not free (a small
    # untrained network barely reacts to the condition, hence the small bound)
    other = collate_teachers(teachers, profile("aggressive"), replace_condition, STYLE_MASK)
    assert float(kl_loss(policy, other).detach()) > 1e-9


def test_kl_averages_per_retry_then_over_retries():
    policy = make_policy()
    w_dep = profile("normal")
    teachers = make_teachers(policy, [2, 9], seed=3)
    both = kl_loss(policy, collate_teachers(teachers, w_dep, replace_condition, STYLE_MASK)).item()
    each = [kl_loss(policy, collate_teachers([t], w_dep, replace_condition, STYLE_MASK)).item() for t in teachers]
    assert both == pytest.approx(np.mean(each), rel=1e-5)
    # a step-weighted mean would be pulled towards the long retry
    step_weighted = (2 * each[0] + 9 * each[1]) / 11
    assert abs(both - step_weighted) > 1e-4


def test_kl_decreases_when_training_on_a_fixed_teacher_set():
    policy = make_policy(1)
    teachers = make_teachers(policy, [6, 10, 4], seed=5)
    batch = collate_teachers(teachers, profile("normal"), replace_condition, STYLE_MASK)
    opt = th.optim.Adam(policy.parameters(), lr=1e-2)
    start = kl_loss(policy, batch).item()
    for _ in range(40):
        opt.zero_grad()
        loss = kl_loss(policy, batch)
        loss.backward()
        opt.step()
    end = kl_loss(policy, batch).item()
    assert end < 0.5 * start


def test_ppo_ablation_raises_the_probability_of_positive_advantage_actions():
    policy = make_policy(2)
    teachers = make_teachers(policy, [8, 8], seed=7)
    batch = collate_teachers(teachers, profile("normal"), replace_condition, STYLE_MASK, policy=policy, gamma=0.9)
    assert ppo_loss(policy, batch, 0.2).item() == pytest.approx(-float((batch.advantages * batch.mask).sum(1).div(8).mean()), abs=1e-5)
    good = (batch.advantages > 0) & (batch.mask > 0)
    opt = th.optim.Adam(policy.parameters(), lr=5e-3)
    before = batch.old_logp[good].mean()
    for _ in range(10):
        opt.zero_grad()
        distill_loss(policy, batch, "ppo", 0.2).backward()
        opt.step()
    with th.no_grad():
        starts = th.zeros(batch.student_obs.shape[0])
        logits, _ = actor_logits(policy, batch.student_obs, batch.pi_state, starts)
        logp = th.log_softmax(logits, -1).reshape(2, 8, -1).gather(-1, batch.actions[..., None]).squeeze(-1)
    assert logp[good].mean() > before


def test_distill_rejects_bad_input():
    policy = make_policy()
    with pytest.raises(ValueError, match="teachers"):
        collate_teachers([], profile("normal"), replace_condition, STYLE_MASK)
    with pytest.raises(ValueError, match="logits"):
        Teacher(obs=th.zeros(3, OBS_DIM), logits=th.zeros(2, 5), actions=th.zeros(3), rewards=th.zeros(3),
                pi_state=(th.zeros(1, 8),) * 2, vf_state=(th.zeros(1, 8),) * 2, condition=profile("normal"))
    batch = collate_teachers(make_teachers(policy, [3]), profile("normal"), replace_condition, STYLE_MASK)
    with pytest.raises(ValueError, match="distill"):
        distill_loss(policy, batch, "mse")


def test_the_student_condition_is_normalised_like_the_policy_inputs_under_vec_normalize():
    """Teachers record the policy's inputs: under SelfPlayVecNormalize already normalised, so
    the student's w_dep must be written with the same normalisation as a rollout would give."""
    pytest.importorskip("cpsim.simulator")
    from cpalgo import CounterPlay
    from cpsim import SelfPlayVecEnv
    from cpsim.envs.selfplay import SelfPlayVecNormalize

    env = SelfPlayVecNormalize(SelfPlayVecEnv(num_worlds=2, max_agents=3, num_scenarios=2, seed=0, episode_steps=12))
    model = CounterPlay("MlpLstmPolicy", env, n_steps=8, batch_size=8, n_epochs=1, seed=0,
                        policy_kwargs=dict(lstm_hidden_size=8, net_arch=[8]))
    env.reset()
    for _ in range(4):  # running statistics away from their start
        env.step(np.random.default_rng(0).integers(0, env.action_space.n, env.num_envs))
    raw = env.get_original_obs()
    w_dep = profile("aggressive")
    layout = env.obs_layout
    expected = env.normalize_obs(layout.replace_condition(raw, np.broadcast_to(w_dep, (raw.shape[0], 10))))
    got = model._student_condition_writer()(th.as_tensor(env.normalize_obs(raw)), th.as_tensor(w_dep))
    np.testing.assert_allclose(got.numpy(), expected, atol=1e-5)
    assert not np.allclose(expected[:, layout.condition],  # the plain writer would be wrong here
                           layout.replace_condition(env.normalize_obs(raw), w_dep)[:, layout.condition])
