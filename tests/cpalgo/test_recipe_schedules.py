"""Learning-rate schedules as recipe settings (cpalgo.recipes.parse_schedule)."""

from __future__ import annotations

import math
import pickle

import pytest
import yaml

from cpalgo.recipes import (
    SELFPLAY_ENV_ID,
    ZOO_DIR,
    CosineSchedule,
    LinearSchedule,
    load_recipe,
    parse_schedule,
    zoo_preprocess_schedules,
)


def test_cosine_schedule_values():
    lr = parse_schedule("cosine(3e-5)", "learning_rate")
    assert isinstance(lr, CosineSchedule)
    # SB3's progress_remaining runs 1 -> 0: lr0 * 0.5 * (1 + cos(pi * (1 - p)))
    assert lr(1.0) == pytest.approx(3e-5)
    assert lr(0.5) == pytest.approx(1.5e-5)
    assert lr(0.0) == pytest.approx(0.0, abs=1e-20)
    assert lr(0.75) == pytest.approx(3e-5 * 0.5 * (1 + math.cos(math.pi * 0.25)))
    assert lr(0.25) == pytest.approx(3e-5 * 0.5 * (1 - math.cos(math.pi * 0.25)))
    # monotone, never outside [0, lr0] even when progress overshoots
    values = [lr(1 - i / 100) for i in range(101)]
    assert all(a >= b for a, b in zip(values, values[1:]))
    assert lr(1.2) == pytest.approx(3e-5) and lr(-0.1) == 0.0
    # the other spellings
    for spec in ("cos_3e-5", "cosine_3e-5", "Cosine( 3e-5 )"):
        assert parse_schedule(spec) == lr


def test_linear_and_constant_schedules():
    lin = parse_schedule("lin_3e-4", "learning_rate")
    assert isinstance(lin, LinearSchedule) and parse_schedule("linear(3e-4)") == lin
    assert lin(1.0) == pytest.approx(3e-4) and lin(0.5) == pytest.approx(1.5e-4) and lin(0.0) == 0.0
    # constants stay plain floats (SB3 builds its own constant schedule, as before)
    for spec in (2e-4, "2e-4", "constant(2e-4)", "const_2e-4"):
        out = parse_schedule(spec)
        assert isinstance(out, float) and out == pytest.approx(2e-4)
    assert parse_schedule(None, "clip_range_vf") is None
    # picklable: SB3 saves the schedule with the model
    assert pickle.loads(pickle.dumps(CosineSchedule(1e-3)))(0.5) == pytest.approx(5e-4)


@pytest.mark.parametrize("spec", ["cosine(x)", "cosine()", "warmup(1e-3)", "cosine(-1e-3)", -1.0, 0,
                                  "nan", True, None, [1e-3]])
def test_bad_schedule_names_the_key(spec):
    with pytest.raises(ValueError, match="learning_rate"):
        parse_schedule(spec, "learning_rate")


def test_recipe_reads_the_schedule_and_names_key_and_file_when_bad(tmp_path):
    post = load_recipe(ZOO_DIR / "counterplay.yml")
    # the post-training default: the seed paper's 3e-5 with a cosine schedule
    assert post.algo_kwargs["learning_rate"] == CosineSchedule(3e-5)
    doc = {SELFPLAY_ENV_ID: {"policy": "MlpLstmPolicy", "n_envs": 8, "n_timesteps": 8,
                             "learning_rate": "cosine(1e-3)", "clip_range": "lin_0.2"}}
    path = tmp_path / "r.yml"
    path.write_text(yaml.safe_dump(doc))
    r = load_recipe(path)
    assert r.algo_kwargs["learning_rate"] == CosineSchedule(1e-3)
    assert r.algo_kwargs["clip_range"] == LinearSchedule(0.2)
    doc[SELFPLAY_ENV_ID]["learning_rate"] = "cosine(fast)"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValueError, match=r"r\.yml: learning_rate"):
        load_recipe(path)


def test_zoo_preprocessing_uses_the_same_parser():
    def original(hp):  # stands in for rl-zoo3's parser: floats only
        assert all(not isinstance(v, str) for k, v in hp.items() if k == "learning_rate")
        return {**hp, "seen": True}

    pre = zoo_preprocess_schedules(original)
    out = pre({"learning_rate": "cosine(3e-5)", "clip_range": 0.2, "n_steps": 8})
    assert out["learning_rate"] == CosineSchedule(3e-5) and out["seen"] and out["clip_range"] == 0.2
    assert zoo_preprocess_schedules(pre) is pre  # installing twice wraps once
    with pytest.raises(ValueError, match="learning_rate"):
        pre({"learning_rate": "cosine(x)"})


@pytest.mark.usefixtures("_one_torch_thread")
def test_cosine_schedule_drives_the_optimizer():
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.env_util import make_vec_env

    env = make_vec_env("CartPole-v1", n_envs=2, seed=0)
    model = RecurrentPPO("MlpLstmPolicy", env, n_steps=16, batch_size=32, n_epochs=1, seed=0,
                         learning_rate=parse_schedule("cosine(3e-5)"),
                         policy_kwargs=dict(lstm_hidden_size=8, net_arch=[8]))
    model.learn(64)
    # after the last update progress_remaining = 1 - 64/64 -> about 0
    lr = model.policy.optimizer.param_groups[0]["lr"]
    assert 0.0 <= lr < 3e-5 * 0.2
