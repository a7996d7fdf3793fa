"""Linear observation encoder, factorisation of a flat policy, and policy distillation
(cpalgo.encoders, cpalgo.anchor.compress)."""

from __future__ import annotations

import functools

import gymnasium as gym
import numpy as np
import pytest
import torch as th

import cpsim
from cpalgo.anchor.compress import DistillConfig, collect_teacher_episodes, distill_losses, distill_policy
from cpalgo.common.policy_utils import policy_step_logits, zero_states
from cpalgo.encoders import (
    ConditionConcat,
    ConditionResidual,
    LinearEncoder,
    add_condition_branch,
    encoder_policy_kwargs,
    factorize_input_layers,
)

FLAT = dict(lstm_hidden_size=16, enable_critic_lstm=False, net_arch=dict(pi=[16], vf=[16]))


@functools.lru_cache(maxsize=1)
def _pool() -> tuple:
    from cpsim.scenario import train_pool

    return tuple(train_pool(3, 0))


def _model(policy_kwargs: dict, seed: int = 0):
    from sb3_contrib import RecurrentPPO

    env = cpsim.SelfPlayVecEnv(list(_pool()), num_worlds=2, max_agents=4, seed=0)
    return RecurrentPPO("MlpLstmPolicy", env, n_steps=8, batch_size=16, seed=seed, device="cpu",
                        policy_kwargs=policy_kwargs)


def _observations(n: int, d: int, seed: int = 0) -> np.ndarray:
    # sparse, bounded, like the driving observation (zero-padded slots)
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, size=(n, d)) * (rng.random((n, d)) < 0.4)
    return x.astype(np.float32)


def _outputs(policy, obs: th.Tensor):
    states = zero_states(policy, obs.shape[1], "cpu")
    logits, values = [], []
    starts = th.ones(obs.shape[1])
    for t in range(obs.shape[0]):
        lg, v, states = policy_step_logits(policy, obs[t], states, starts)
        starts = th.zeros(obs.shape[1])
        logits.append(lg)
        values.append(v)
    return th.stack(logits), th.stack(values)


def test_linear_encoder_shapes_and_bad_arguments():
    space = gym.spaces.Box(-1, 1, (20,), np.float32)
    enc = LinearEncoder(space, features_dim=8)
    assert enc(th.zeros(5, 20)).shape == (5, 8) and enc.linear.bias is None
    with pytest.raises(ValueError, match="features_dim"):
        LinearEncoder(space, features_dim=21)
    with pytest.raises(ValueError, match="flat Box"):
        LinearEncoder(gym.spaces.Discrete(3))


@pytest.mark.parametrize("critic_lstm", [False, True])
def test_full_rank_factorisation_reproduces_the_flat_policy(critic_lstm):
    flat = dict(FLAT, enable_critic_lstm=critic_lstm)
    source = _model(flat).policy
    # rank = all stacked input rows (4 * 16 actor LSTM + 16 critic layer, or + 4 * 16 critic
    # LSTM): the factorisation is exact
    rank = 128 if critic_lstm else 80
    target = _model(encoder_policy_kwargs(flat, rank), seed=1).policy
    d = source.observation_space.shape[0]
    report = factorize_input_layers(source, target, _observations(400, d))
    assert report["rank"] == rank and report["relative_error"] < 1e-10
    obs = th.as_tensor(_observations(6 * 5, d, seed=3)).reshape(6, 5, d)
    with th.no_grad():
        (l1, v1), (l2, v2) = _outputs(source, obs), _outputs(target, obs)
    assert th.allclose(l1, l2, atol=1e-4) and th.allclose(v1, v2, atol=1e-4)


def test_low_rank_factorisation_is_the_best_fit_on_its_data():
    source = _model(FLAT).policy
    target = _model(encoder_policy_kwargs(FLAT, 24), seed=1).policy
    d = source.observation_space.shape[0]
    x = _observations(500, d)
    # critic_weight 1: the fit minimises the plain (unweighted) error that is compared below
    report = factorize_input_layers(source, target, x, critic_weight=1.0)
    assert 0 < report["relative_error"] < 1
    # any other rank-24 map does worse on the same data: a random one, and plain truncated
    # SVD of the weights (which ignores the data)
    w = th.cat([source.lstm_actor.weight_ih_l0, source.critic.weight]).detach().double().numpy()
    u, s, vt = np.linalg.svd(w, full_matrices=False)
    naive = (u[:, :24] * s[:24]) @ vt[:24]
    exact = x @ w.T
    naive_err = np.sum((exact - x @ naive.T) ** 2) / np.sum(exact ** 2)
    assert report["relative_error"] <= naive_err + 1e-9
    # biases and heads are copied unchanged
    assert th.equal(target.action_net.weight, source.action_net.weight)
    assert th.equal(target.lstm_actor.bias_ih_l0, source.lstm_actor.bias_ih_l0)


def test_factorisation_needs_an_encoder_target_and_enough_data():
    source = _model(FLAT).policy
    d = source.observation_space.shape[0]
    with pytest.raises(ValueError, match="LinearEncoder"):
        factorize_input_layers(source, _model(FLAT).policy, _observations(100, d))
    target = _model(encoder_policy_kwargs(FLAT, 24)).policy
    with pytest.raises(ValueError, match="at least 24 rows"):
        factorize_input_layers(source, target, _observations(10, d))
    with pytest.raises(ValueError, match="observations"):
        factorize_input_layers(source, target, _observations(100, d - 1))
    with pytest.raises(ValueError, match="NaN"):
        factorize_input_layers(source, target, np.full((100, d), np.nan, np.float32))
    with pytest.raises(ValueError, match="critic_weight"):
        factorize_input_layers(source, target, _observations(100, d), critic_weight=float("nan"))
    # rank above the 80 stacked input rows
    with pytest.raises(ValueError, match="exceeds the 80 input rows"):
        factorize_input_layers(source, _model(encoder_policy_kwargs(FLAT, 96)).policy, _observations(200, d))
    # a target that differs elsewhere (wider heads) is refused, not half-copied
    wider = _model(encoder_policy_kwargs(dict(FLAT, net_arch=dict(pi=[32], vf=[16])), 24)).policy
    with pytest.raises(ValueError, match="differ outside the input layers: mlp_extractor.policy_net"):
        factorize_input_layers(source, wider, _observations(100, d))
    split = _model(dict(encoder_policy_kwargs(FLAT, 24), share_features_extractor=False)).policy
    with pytest.raises(ValueError, match="share_features_extractor=False"):
        factorize_input_layers(source, split, _observations(100, d))


def test_distill_config_rejects_unknown_and_bad_values():
    with pytest.raises(ValueError, match="unknown keys"):
        DistillConfig.from_dict({"rounds": 1, "iterations": 2})
    with pytest.raises(ValueError, match="beta"):
        DistillConfig(beta=2.0)
    with pytest.raises(ValueError, match="rounds"):
        DistillConfig(rounds=-1)
    with pytest.raises(ValueError, match="rounds: must be an integer"):
        DistillConfig(rounds=1.5)
    with pytest.raises(ValueError, match="value_coef"):
        DistillConfig(value_coef=float("nan"))
    with pytest.raises(ValueError, match="num_worlds"):
        DistillConfig(num_worlds=0)


def test_teacher_labels_and_zero_loss_for_an_identical_student():
    teacher = _model(FLAT).policy
    sim = cpsim.Simulator(list(_pool()), num_worlds=2, max_agents=4, seed=0)
    batch = collect_teacher_episodes(teacher, teacher, sim, beta=1.0, rng=np.random.default_rng(0),
                                     config=DistillConfig(panel_share=1.0, eval_task_share=1.0))
    T, N, D = batch.obs.shape
    assert N == 8 and batch.mask.any() and batch.log_probs.shape == (T, N, 12)
    # a student that is the teacher: no disagreement during the rollout, zero loss on it
    assert batch.kl == pytest.approx(0.0, abs=1e-6) and batch.agreement == 1.0
    kl, mse = distill_losses(teacher, batch.obs, batch.log_probs, batch.values, batch.mask)
    assert kl.item() == pytest.approx(0.0, abs=1e-5) and mse.item() == pytest.approx(0.0, abs=1e-8)
    # the conditions drawn: every agent a panel style and the evaluation task fields
    from cpsim.conditions import FIELD_INDEX, PANEL, STYLE_MASK, TASK_FIELDS, criterion_task_fields, profile

    raw = sim.conditions.reshape(-1, STYLE_MASK.size).numpy()
    styles = np.stack([profile(p)[STYLE_MASK] for p in PANEL])
    assert all(np.any(np.all(np.isclose(styles, row[STYLE_MASK]), axis=1)) for row in raw)
    assert np.allclose(raw[:, [FIELD_INDEX[f] for f in TASK_FIELDS]], criterion_task_fields())


def test_distillation_moves_the_student_towards_the_teacher():
    teacher = _model(FLAT, seed=0).policy
    student = _model(encoder_policy_kwargs(FLAT, 24), seed=5)
    sim = cpsim.Simulator(list(_pool()), num_worlds=3, max_agents=4, seed=1)
    cfg = DistillConfig(rounds=1, num_worlds=3, epochs=1, batch_sequences=12, learning_rate=3e-3)
    before = collect_teacher_episodes(student.policy, teacher, sim, 0.0, np.random.default_rng(9), cfg)
    history = distill_policy(student, teacher, list(_pool()), DistillConfig.from_dict(
        dict(rounds=2, num_worlds=3, epochs=6, batch_sequences=12, learning_rate=3e-3)),
        max_agents=4, seed=0, log=None)
    assert [row["round"] for row in history] == [0, 1]
    assert all(row["transitions"] > 0 for row in history)
    sim = cpsim.Simulator(list(_pool()), num_worlds=3, max_agents=4, seed=1)
    after = collect_teacher_episodes(student.policy, teacher, sim, 0.0, np.random.default_rng(9), cfg)
    assert after.kl < 0.5 * before.kl


def test_compress_anchor_command_writes_an_encoder_checkpoint_and_report(tmp_path, capsys):
    import json

    from sb3_contrib import RecurrentPPO

    from cpalgo.cli import main

    anchor = tmp_path / "flat.zip"
    _model(FLAT).save(anchor)
    out = tmp_path / "fast" / "anchor.zip"
    assert main(["compress-anchor", "--anchor", str(anchor), "--out", str(out), "--features-dim", "12",
                 "--rounds", "1", "--worlds", "2", "--epochs", "1", "--max-agents", "4", "--threads", "1",
                 "--scenarios", "2"]) == 0
    loaded = RecurrentPPO.load(out, device="cpu")
    assert isinstance(loaded.policy.features_extractor, LinearEncoder)
    assert loaded.policy.features_extractor.features_dim == 12
    report = json.loads((tmp_path / "fast" / "anchor.json").read_text())
    assert report["features_dim"] == 12 and len(report["rounds"]) == 1 and 0 < report["fit"]["relative_error"] < 1
    # continue distilling the output: no new factorisation, the weights carried over
    again = tmp_path / "again.zip"
    assert main(["compress-anchor", "--anchor", str(anchor), "--out", str(again), "--features-dim", "12",
                 "--rounds", "0", "--init", str(out), "--max-agents", "4", "--scenarios", "2"]) == 0
    assert th.equal(RecurrentPPO.load(again, device="cpu").policy.features_extractor.linear.weight,
                    loaded.policy.features_extractor.linear.weight)
    assert json.loads((tmp_path / "again.json").read_text())["fit"] == {"init": str(out)}
    with pytest.raises(SystemExit):
        main(["compress-anchor", "--anchor", str(anchor), "--out", str(again), "--features-dim", "8",
              "--init", str(out), "--max-agents", "4", "--scenarios", "2"])
    assert "is not a 8-feature encoder network" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["compress-anchor", "--anchor", str(tmp_path / "missing.zip"), "--out", str(out)])
    assert "--anchor: no such checkpoint" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["compress-anchor", "--anchor", str(anchor), "--out", str(out), "--features-dim", "0"])
    assert "--features-dim: must be a positive integer" in capsys.readouterr().err


def test_fast_recipe_names_the_encoder_for_load_recipe_and_rl_zoo3():
    from cpalgo.recipes import load_recipe

    kwargs = load_recipe("zoo/counterplay_fast.yml").algo_kwargs["policy_kwargs"]
    assert kwargs["features_extractor_class"] is LinearEncoder
    assert kwargs["features_extractor_kwargs"] == {"features_dim": 128}
    pytest.importorskip("rl_zoo3")
    import rl_zoo3.exp_manager

    from cpalgo.zoo import register

    register()
    assert rl_zoo3.exp_manager.LinearEncoder is LinearEncoder and rl_zoo3.utils.LinearEncoder is LinearEncoder


def test_condition_residual_adds_a_function_of_the_condition_slice_only():
    space = gym.spaces.Box(-1, 1, (30,), np.float32)
    enc = ConditionResidual(space, condition_start=5, condition_size=4, hidden=8)
    th.nn.init.normal_(enc.branch[-1].weight)  # a trained branch
    x = th.as_tensor(_observations(6, 30))
    y = enc(x)
    assert y.shape == (6, 30) and not th.allclose(y, x)
    x2 = x.clone()
    x2[:, 10:] += 0.5  # outside the condition slice: passes straight through
    assert th.allclose(enc(x2) - x2, y - x)
    x3 = x.clone()
    x3[:, 5:9] = -x3[:, 5:9]  # the condition changes: the added term changes
    assert not th.allclose(enc(x3) - x3, y - x)
    with pytest.raises(ValueError, match="condition_start"):
        ConditionResidual(space, condition_start=28, condition_size=4)
    with pytest.raises(ValueError, match="hidden"):
        ConditionResidual(space, hidden=0)


def test_add_condition_branch_keeps_a_flat_policy_function():
    source = _model(FLAT).policy
    d = source.observation_space.shape[0]
    target = _model(dict(FLAT, features_extractor_class=ConditionResidual,
                         features_extractor_kwargs=dict(condition_start=17, condition_size=10)), seed=1).policy
    missing = add_condition_branch(source, target)
    assert missing and all(".branch." in k for k in missing)
    obs = th.as_tensor(_observations(5 * 3, d, seed=2)).reshape(5, 3, d)
    for got, want in zip(_outputs(target, obs), _outputs(source, obs)):
        assert th.allclose(got, want, atol=1e-6)
    with pytest.raises(ValueError, match="ConditionResidual or ConditionConcat"):
        add_condition_branch(source, _model(FLAT).policy)


def test_condition_concat_appends_the_encoding_and_converts_a_flat_policy():
    space = gym.spaces.Box(-1, 1, (30,), np.float32)
    enc = ConditionConcat(space, condition_start=5, condition_size=4, hidden=8)
    x = th.as_tensor(_observations(6, 30))
    y = enc(x)
    assert y.shape == (6, 38) and enc.features_dim == 38 and th.equal(y[:, :30], x)
    source = _model(FLAT).policy
    d = source.observation_space.shape[0]
    target = _model(dict(FLAT, features_extractor_class=ConditionConcat,
                         features_extractor_kwargs=dict(condition_start=17, condition_size=10, hidden=8)),
                    seed=1).policy
    add_condition_branch(source, target)
    assert target.lstm_actor.weight_ih_l0.shape[1] == d + 8
    assert th.count_nonzero(target.lstm_actor.weight_ih_l0[:, d:]) == 0
    obs = th.as_tensor(_observations(5 * 3, d, seed=3)).reshape(5, 3, d)
    for got, want in zip(_outputs(target, obs), _outputs(source, obs)):
        assert th.allclose(got, want, atol=1e-6)
