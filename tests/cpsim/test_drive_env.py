"""cpsim/Drive-v0: env checkers, regimes, vector env, learning, rendering, bad input."""

from __future__ import annotations

import warnings

import gymnasium
import numpy as np
import pytest

import cpsim  # noqa: F401  (registers cpsim/Drive-v0)
from cpsim.scenario import generate

STEPS = 15


pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def scenarios():
    return [generate("intersection", 2), generate("t_junction", 3)]


@pytest.fixture(scope="module")
def ppo_model(scenarios):
    """A tiny untrained PPO used as co-player model."""
    from stable_baselines3 import PPO

    from cpsim.envs.drive import DriveEnv

    env = DriveEnv(scenarios, episode_steps=STEPS, max_agents=6)
    return PPO("MlpPolicy", env, n_steps=32, batch_size=32, seed=0, device="cpu",
               policy_kwargs=dict(net_arch=[16]))


def make(scenarios, **kw):
    from cpsim.envs.drive import DriveEnv

    kw.setdefault("episode_steps", STEPS)
    kw.setdefault("max_agents", 6)
    return DriveEnv(scenarios, **kw)


def test_gymnasium_and_sb3_env_checkers_pass_without_warnings(scenarios):
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # through gymnasium.make so the env has a spec (the checker re-makes it per render mode)
        env = gymnasium.make("cpsim/Drive-v0", scenarios=scenarios, episode_steps=STEPS, max_agents=6,
                             render_mode="rgb_array").unwrapped
        gym_check(env, skip_render_check=False)
        sb3_check(make(scenarios), warn=True)


def test_gymnasium_make_and_episode(scenarios):
    env = gymnasium.make("cpsim/Drive-v0", scenarios=scenarios, episode_steps=STEPS, max_agents=6)
    obs, info = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape and obs.dtype == np.float32
    assert info["scenario_id"] in {s.id for s in scenarios}
    for t in range(STEPS + 1):  # noqa: B007 (t is read after the loop)
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert isinstance(reward, float)
        if terminated or truncated:
            break
    assert terminated or truncated
    assert info["outcome"] in ("goal", "collision", "offroad", "timeout")
    assert truncated == (info["outcome"] == "timeout")
    assert t + 1 <= STEPS


@pytest.mark.parametrize("regime", ["replay", "idm", "static", "policy", "aggressive", "normal",
                                    "cautious", "mix", "expert"])
def test_every_regime_runs_an_episode(scenarios, ppo_model, regime):
    from cpsim.conditions import deployment_condition, profile
    from cpsim.envs.regimes import MIX_PROFILES

    env = make(scenarios, regime=regime, coplayer_model=ppo_model, condition="normal", max_agents=5)
    env.reset(seed=1, options={"scenario_index": 0})
    ctrl = env.sim.controllers.cpu().numpy()[0]
    co = env.driver.coplayer_mask(env.sim)[0]
    assert ctrl[0] == 0 and co.any()
    expected = {"replay": 1, "expert": 1, "idm": 2, "static": 3}.get(regime, 0)
    assert np.all(ctrl[co] == expected)
    cond = env.sim.conditions.cpu().numpy()[0]
    # the ego's condition: the normal style with the evaluation criterion's task fields
    np.testing.assert_allclose(cond[0], deployment_condition("normal"))
    assert env.sim.config.goal_criterion == "evaluation"
    if regime in ("aggressive", "normal", "cautious"):
        np.testing.assert_allclose(cond[co], np.broadcast_to(profile(regime), cond[co].shape))
    if regime == "mix":
        choice = env.driver.mix_choice[0][co]
        for c, k in zip(cond[co], choice):
            np.testing.assert_allclose(c, profile(MIX_PROFILES[k]))
    done, n = False, 0
    while not done:
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        done = terminated or truncated
        n += 1
        assert n <= STEPS
    assert "outcome" in info


def test_policy_regime_coplayers_follow_the_model(scenarios):
    """A callable co-player model that always brakes hard: co-players slow down, ego untouched."""
    calls = []

    def brake(obs):
        calls.append(obs.shape)
        return np.zeros(obs.shape[0], np.int64)  # jerk -15, lateral -4

    env = make(scenarios, regime="policy", coplayer_model=brake)
    env.reset(seed=0, options={"scenario_index": 0})
    co = env.driver.coplayer_mask(env.sim)[0]
    v0 = env.sim.speed.cpu().numpy()[0].copy()
    for _ in range(5):
        env.step(7)  # ego: zero jerk
    v1 = env.sim.speed.cpu().numpy()[0]
    alive = env.sim.alive.cpu().numpy()[0]
    assert calls and all(s[1] == env.observation_space.shape[0] for s in calls)
    assert calls[0][0] == co.sum()
    braked = co & alive & (v0 > 1.0)
    assert braked.any() and np.all(v1[braked] < v0[braked])


def test_mix_rotates_the_profiles_over_the_coplayers():
    """mix: the k-th co-player of each world (slot order) gets aggressive / normal / cautious
    for k % 3 = 0 / 1 / 2; the same every reset and whatever the seed (no random draw)."""
    from cpsim.conditions import profile
    from cpsim.envs.regimes import MIX_PROFILES, TrafficDriver
    from tests.cpsim.scenes import agent, make_scenario

    sc = make_scenario([agent(10.0 * i, 3.7 * (i % 2), speed=5.0, goal=(10.0 * i + 100.0, 3.7 * (i % 2)))
                        for i in range(8)])
    sim = cpsim.Simulator([sc], num_worlds=3, max_agents=8, seed=0)
    table = np.stack([profile(p) for p in MIX_PROFILES])
    seen = []
    for seed in (0, 1):
        driver = TrafficDriver("mix", lambda obs: np.full(obs.shape[0], 7), seed=seed)
        for _ in range(2):
            sim.reset(conditions=cpsim.profile("normal"))
            driver.assign(sim)
            co = driver.coplayer_mask(sim)
            cond = sim.conditions.cpu().numpy()
            assert co.sum(1).tolist() == [7, 7, 7]
            for w in range(3):
                slots = np.flatnonzero(co[w])
                want = np.arange(slots.size) % 3
                assert driver.mix_choice[w, slots].tolist() == want.tolist()
                np.testing.assert_allclose(cond[w, slots], table[want])
                np.testing.assert_allclose(cond[w, 0], profile("normal"))  # the ego keeps its own
            seen.append(driver.mix_choice.copy())
    assert all(np.array_equal(seen[0], x) for x in seen)


def test_recurrent_coplayer_state_is_kept_per_slot(scenarios):
    from sb3_contrib import RecurrentPPO

    env = make(scenarios)
    model = RecurrentPPO("MlpLstmPolicy", env, n_steps=16, batch_size=16, seed=0, device="cpu",
                         policy_kwargs=dict(lstm_hidden_size=8, net_arch=[8]))
    env2 = make(scenarios, regime="normal", coplayer_model=model)
    env2.reset(seed=0, options={"scenario_index": 0})
    env2.step(7)
    state = env2.driver._state
    assert state is not None and state[0].shape[1] == env2.sim.num_worlds * env2.sim.max_agents
    co = env2.driver.coplayer_mask(env2.sim)[0]
    assert np.any(state[0][:, co] != 0) and np.all(state[0][:, ~co] == 0)


@pytest.mark.parametrize("algo", ["PPO", "A2C", "DQN", "RecurrentPPO"])
def test_short_learn(scenarios, algo):
    import sb3_contrib
    import stable_baselines3

    cls = getattr(stable_baselines3, algo, None) or getattr(sb3_contrib, algo)
    env = make(scenarios)
    # small networks: the test checks the plumbing, torch on 2 shared cores is the slow part
    kw = dict(seed=0, device="cpu", policy_kwargs=dict(net_arch=[16]))
    if algo == "PPO":
        kw.update(n_steps=64, batch_size=64, n_epochs=1)
    elif algo == "A2C":
        kw.update(n_steps=32)
    elif algo == "DQN":
        kw.update(learning_starts=32, buffer_size=500, train_freq=8)
    else:
        kw.update(n_steps=64, batch_size=64, n_epochs=1, policy_kwargs=dict(lstm_hidden_size=16, net_arch=[16]))
    policy = "MlpLstmPolicy" if algo == "RecurrentPPO" else "MlpPolicy"
    model = cls(policy, env, **kw)
    model.learn(total_timesteps=128)
    assert model.num_timesteps >= 128
    action, _ = model.predict(env.reset(seed=0)[0], deterministic=True)
    assert env.action_space.contains(int(action))


def test_make_vec_uses_one_batched_simulator(scenarios):
    from cpsim.envs.drive import DriveVectorEnv

    venv = gymnasium.make_vec("cpsim/Drive-v0", num_envs=3, scenarios=scenarios, episode_steps=STEPS,
                              max_agents=4)
    assert isinstance(venv.unwrapped, DriveVectorEnv)
    assert venv.unwrapped.sim.num_worlds == 3
    obs, _ = venv.reset(seed=0)
    assert obs.shape == (3, venv.single_observation_space.shape[0]) and obs.dtype == np.float32
    ended = np.zeros(3, bool)
    autoreset = np.zeros(3, bool)
    for _ in range(STEPS + 2):
        obs, rew, term, trunc, infos = venv.step(venv.action_space.sample())
        # NEXT_STEP autoreset: the step after an end returns a fresh episode with reward 0
        assert np.all(rew[autoreset] == 0) and not np.any((term | trunc)[autoreset])
        done = term | trunc
        if done.any():
            assert set(infos["outcome"][done]) <= {"goal", "collision", "offroad", "timeout"}
            assert np.array_equal(infos["_outcome"], done)
        ended |= done
        autoreset = done
    assert ended.all()
    venv.close()


def test_rendering_changes_between_steps(scenarios):
    env = make(scenarios, render_mode="rgb_array", camera="ego")
    env.reset(seed=0)
    f0 = env.render()
    env.step(10)
    env.step(10)
    f1 = env.render()
    assert f0.shape == (480, 480, 3) and f0.dtype == np.uint8
    assert len(np.unique(f0.reshape(-1, 3), axis=0)) > 5
    assert not np.array_equal(f0, f1)


def test_bad_input(scenarios):
    from cpsim.envs.regimes import TrafficDriver

    with pytest.raises(ValueError, match="accepted"):
        make(scenarios, regime="rush_hour")
    with pytest.raises(ValueError, match="needs a co-player model"):
        make(scenarios, regime="mix")
    with pytest.raises(ValueError, match="accepted"):
        make(None, family="highway")
    with pytest.raises(ValueError, match="profile"):
        make(scenarios, condition="sporty")
    with pytest.raises(ValueError, match="render_mode"):
        make(scenarios, render_mode="ansi")
    with pytest.raises(ValueError, match="only one"):
        make(scenarios, family="intersection")
    with pytest.raises(ValueError, match="condition applies"):
        TrafficDriver("idm", condition="normal")
    with pytest.raises(ValueError, match="seed"):
        make(scenarios, seed=-1)
    env = make(scenarios)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="accepted: 0..11"):
        env.step(12)
    with pytest.raises(ValueError, match="accepted: 0..11"):
        env.step(-1)
    with pytest.raises(ValueError, match="scenario_index"):
        env.reset(options={"scenario_index": 5})
    with pytest.raises(ValueError, match="unknown key"):
        env.reset(options={"speed": 3})


def test_classic_dynamics_action_space(scenarios):
    env = make(scenarios, dynamics="classic")
    assert env.action_space.n == 91
    env.reset(seed=0)
    env.step(90)


def test_zoo_defaults_only_replace_the_zoo_default_file(tmp_path):
    """`--gym-packages cpsim` makes rl-zoo3 read our YAML for cpsim/ ids; --conf-file wins."""
    import types

    import yaml

    from cpsim.envs.zoo_support import hyperparams_file, install, zoo_default_file

    zoo_default = zoo_default_file("ppo")
    if zoo_default is None:
        pytest.skip("rl_zoo3 is not installed")

    class FakeManager:
        def __init__(self, algo, gym_id, config):
            self.algo, self.env_name, self.config = algo, types.SimpleNamespace(gym_id=gym_id), config

        def read_hyperparameters(self):
            return self.config

    install(FakeManager)
    install(FakeManager)  # idempotent
    assert FakeManager("ppo", "cpsim/Drive-v0", zoo_default).read_hyperparameters() == hyperparams_file("ppo")
    assert FakeManager("ppo", "CartPole-v1", zoo_default).read_hyperparameters() == zoo_default
    mine = str(tmp_path / "mine.yml")
    assert FakeManager("ppo", "cpsim/Drive-v0", mine).read_hyperparameters() == mine
    for algo in ("ppo", "a2c", "dqn", "ppo_lstm"):
        with open(hyperparams_file(algo)) as f:
            assert "cpsim/Drive-v0" in yaml.safe_load(f)


def test_drivers_sharing_one_simulator_own_their_worlds(scenarios):
    """Evaluation style: one driver per regime on one simulator; reassigning worlds moves them."""
    from cpsim import Simulator
    from cpsim.envs.regimes import TrafficDriver

    sim = Simulator(scenarios, num_worlds=2, max_agents=5, config={"episode_steps": STEPS})
    seen = {"a": [], "b": []}

    def model(name):
        def act(obs):
            seen[name].append(obs.shape[0])
            return np.full(obs.shape[0], 7)
        return act

    a, b = TrafficDriver("policy", model("a")), TrafficDriver("normal", model("b"))
    sim.reset(scenario_index=np.array([0, 0]))
    a.assign(sim, [0])
    b.assign(sim, [1])
    n_co = int(a.coplayer_mask(sim, [0]).sum())
    actions = np.zeros((2, 5), np.int64)
    a.act(out=actions)
    b.act(out=actions)
    assert seen["a"] == [n_co] and seen["b"] == [n_co]
    assert np.all(actions[:, 0] == 0)  # the ego slot is never a co-player
    # next chunk: worlds swap regimes; a must no longer drive world 0
    sim.reset(scenario_index=np.array([0, 0]))
    a.assign(sim, [1])
    b.assign(sim, [0])
    a.act()
    b.act()
    assert seen["a"] == [n_co, n_co] and seen["b"] == [n_co, n_co]
    a.release()
    assert a.act().sum() == 0


@pytest.mark.parametrize("condition", ["cautious", "normal", "aggressive", "cautious-normal"])
def test_fixed_deployment_condition_keeps_one_goal_test(condition):
    """A fixed deployment condition changes style fields only: the ego passes its goal at
    10 m/s (faster than the cautious profile's goal speed of 5 m/s) and the goal counts
    under every profile, at the same step, with the same task fields in its observation."""
    from cpsim.conditions import STYLE_MASK
    from cpsim.envs.drive import DriveEnv
    from tests.cpsim.scenes import agent, make_scenario

    sc = make_scenario([agent(0.0, 0.0, speed=10.0, goal=(12.0, 0.0))])
    env = DriveEnv([sc], condition=condition, episode_steps=30, max_agents=2)
    assert env.sim.config.goal_criterion == "evaluation"
    obs, _ = env.reset(seed=0)
    task = env.obs_layout.condition.start + np.flatnonzero(~STYLE_MASK)
    reference = DriveEnv([sc], condition="normal", episode_steps=30, max_agents=2).reset(seed=0)[0]
    np.testing.assert_array_equal(obs[task], reference[task])
    for t in range(1, 31):  # noqa: B007 (t is read after the loop)
        _, _, terminated, truncated, info = env.step(2 * 3 + 1)  # zero jerks: constant 10 m/s
        if terminated or truncated:
            break
    assert info["outcome"] == "goal" and t == 11  # 1 m per step: within 2 m of x = 12 at x = 11


def test_training_condition_keeps_per_agent_task_fields():
    """condition="train": every agent keeps the goal_radius / goal_speed drawn from p_train."""
    from cpsim.conditions import STYLE_MASK
    from cpsim.envs.drive import DriveEnv
    from tests.cpsim.scenes import agent, make_scenario

    sc = make_scenario([agent(0.0, 0.0, speed=10.0, goal=(12.0, 0.0))])
    env = DriveEnv([sc], condition="train", episode_steps=30, max_agents=2, seed=0)
    assert env.sim.config.goal_criterion == "condition"
    seen = set()
    for seed in range(4):
        env.reset(seed=seed)
        seen.add(tuple(env.sim.conditions.cpu().numpy()[0, 0, ~STYLE_MASK].round(4)))
    assert len(seen) == 4  # drawn per episode, not the evaluation criterion


SCORE_KEYS = {"at_fault_collision", "comfort", "lane_align", "lane_center", "score"}


def test_spec_horizon_and_episode_end_scores(scenarios):
    """spec.max_episode_steps is the fixed 91-step horizon; the last info carries the
    episode's at-fault flag, comfort, lane metrics and score (cpsim.scoring)."""
    env = gymnasium.make("cpsim/Drive-v0", scenarios=scenarios, max_agents=6)
    assert env.spec.max_episode_steps == 91 == env.unwrapped.sim.config.episode_steps
    short = gymnasium.make("cpsim/Drive-v0", scenarios=scenarios, episode_steps=STEPS, max_agents=6)
    short.reset(seed=0)
    done = False
    while not done:
        _, _, terminated, truncated, info = short.step(7)
        done = terminated or truncated
    assert SCORE_KEYS <= set(info)
    assert isinstance(info["at_fault_collision"], bool)
    assert 0.0 <= info["comfort"] <= 1.0 and 0.0 <= info["score"] <= 100.0
    assert (info["score"] > 0) == (info["outcome"] == "goal" and not info["at_fault_collision"])


def test_make_vec_seed_lists_and_single_env_info_keys(scenarios):
    """reset(seed=[...]) seeds every sub-environment; seed=s seeds sub-env i with s + i, as
    DriveEnv seeded with s + i; vector infos carry the single env's keys."""
    from cpsim.envs.drive import DriveEnv

    def venv():
        return gymnasium.make_vec("cpsim/Drive-v0", num_envs=3, scenarios=scenarios, episode_steps=STEPS,
                                  max_agents=4, condition="train")

    a, b = venv(), venv()
    obs_a, info = a.reset(seed=[5, 6, 7])
    obs_b, _ = b.reset(seed=[5, 99, 7])
    np.testing.assert_array_equal(obs_a[[0, 2]], obs_b[[0, 2]])
    assert set(info) >= {"scenario_id", "_scenario_id", "step", "_step"} and list(info["step"]) == [0, 0, 0]
    obs_c, _ = b.reset(seed=5)  # = [5, 6, 7]
    np.testing.assert_array_equal(obs_a, obs_c)
    single = DriveEnv(scenarios, episode_steps=STEPS, max_agents=4, condition="train")
    np.testing.assert_array_equal(single.reset(seed=6)[0], obs_a[1])
    with pytest.raises(ValueError, match="one seed per sub-environment"):
        a.reset(seed=[1, 2])
    seen_end = False
    for _ in range(STEPS + 1):
        _, _, term, trunc, infos = a.step(np.full(3, 7))
        assert list(infos["scenario_id"]) == a.unwrapped.core.scenario_ids()
        assert infos["_step"].all() and infos["step"].dtype == np.int64
        ended = term | trunc
        if ended.any():
            seen_end = True
            for key in SCORE_KEYS:
                assert np.array_equal(infos[f"_{key}"], ended)
            assert np.all((infos["score"] >= 0) & (infos["score"] <= 100))
    assert seen_end
    a.close()
    b.close()


def test_human_render_mode_runs_headless(scenarios, monkeypatch):
    """render_mode="human" draws every step into a matplotlib window (none opens under Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    env = make(scenarios, render_mode="human", render_size=(64, 64))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env.reset(seed=0)
        env.step(7)
        assert env.render() is None
    assert env._viewer._image.get_array().shape[:2] == (64, 64)
    env.close()
    venv = gymnasium.make_vec("cpsim/Drive-v0", num_envs=2, scenarios=scenarios, episode_steps=STEPS,
                              max_agents=4, render_mode="human", render_size=(32, 32))
    venv.reset(seed=0)
    venv.step(np.full(2, 7))
    assert venv.render() is None
    venv.close()


def test_policy_regime_accepts_a_checkpoint_path(scenarios, ppo_model, tmp_path):
    """A checkpoint path works where a model does (so YAML files and command lines can name one)."""
    path = tmp_path / "coplayer.zip"
    ppo_model.save(path)
    env = make(scenarios, regime="normal", coplayer_model=str(path))
    assert type(env.driver.model).__name__ == "PPO"
    env.reset(seed=0)
    env.step(7)
    with pytest.raises(ValueError, match="coplayer_model"):
        make(scenarios, regime="normal", coplayer_model=str(tmp_path / "missing.zip"))
    (tmp_path / "junk.zip").write_text("not a checkpoint")
    with pytest.raises(ValueError, match="cannot load"):
        make(scenarios, regime="normal", coplayer_model=str(tmp_path / "junk.zip"))

