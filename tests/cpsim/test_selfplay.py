"""SelfPlayVecEnv: SB3 VecEnv contract, inactive-slot contract, copies, wrappers, learning."""

from __future__ import annotations

import numpy as np
import pytest

from cpsim.scenario import generate

W, A = 2, 6


pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py

STEPS = 12  # short episodes keep the tests fast


@pytest.fixture(scope="module")
def scenarios():
    return [generate("intersection", 0), generate("merge", 1)]


@pytest.fixture(scope="module")
def env(scenarios):
    from cpsim.envs.selfplay import SelfPlayVecEnv

    e = SelfPlayVecEnv(scenarios, num_worlds=W, max_agents=A, seed=3, episode_steps=STEPS)
    yield e
    e.close()


def _random_actions(env, rng):
    return rng.integers(0, env.action_space.n, size=env.num_envs)


def test_spaces_and_attributes(env):
    from gymnasium import spaces

    assert env.num_envs == W * A
    assert isinstance(env.observation_space, spaces.Box)
    assert env.observation_space.shape == (env.obs_layout.size,)
    assert env.action_space == spaces.Discrete(12)
    assert env.num_worlds == W and env.max_agents == A and env.sim.num_worlds == W
    assert env.get_attr("max_agents", [0, 3]) == [A, A]
    env.set_attr("render_worlds", 2)
    assert env.render_worlds == 2
    assert env.env_method("active_mask", indices=[1])[0].shape == (W * A,)
    assert env.env_is_wrapped(object) == [False] * env.num_envs


def test_reset_obs_copy_and_inactive_slots_zero(env):
    obs = env.reset()
    assert obs.dtype == np.float32 and obs.shape == (W * A, env.obs_layout.size)
    active = env.active_mask()
    policy = env.sim.policy_mask.cpu().numpy().reshape(-1)
    np.testing.assert_array_equal(active, policy)
    assert active.any()
    assert np.all(obs[~active] == 0)
    assert np.any(obs[active] != 0, axis=1).all()
    # a copy, not a view onto simulator memory
    before = obs.copy()
    env.step(np.zeros(env.num_envs, np.int64))
    np.testing.assert_array_equal(obs, before)


def test_episode_contract_infos_and_autoreset(env):
    rng = np.random.default_rng(0)
    env.seed(5)
    env.reset()
    prev_active = env.active_mask()
    saw_done = saw_timeout = False
    for _ in range(2 * STEPS + 2):
        obs, rew, done, infos = env.step(_random_actions(env, rng))
        assert obs.dtype == np.float32 and rew.dtype == np.float32 and done.dtype == bool
        assert len(infos) == env.num_envs
        active = env.active_mask()
        assert [i["active"] for i in infos] == active.tolist()
        # inactive before the step: reward 0, done only to end an empty episode
        empty = np.array([bool(i.get("empty")) for i in infos])
        assert np.all(rew[~prev_active] == 0) and not np.any(done & ~prev_active & ~empty)
        assert not np.any(empty & prev_active)
        # inactive now: zero observation (unless a done index just got a fresh episode)
        assert np.all(obs[~active] == 0)
        for i in np.flatnonzero(done & ~empty):
            info = infos[i]
            assert {"terminal_observation", "TimeLimit.truncated", "is_success", "outcome", "active",
                    "at_fault_collision", "comfort", "lane_align", "lane_center", "score"} <= set(info)
            assert 0.0 <= info["comfort"] <= 1.0 and 0.0 <= info["score"] <= 100.0
            assert info["score"] == 0.0 or (info["outcome"] == "goal" and not info["at_fault_collision"])
            assert info["outcome"] in ("goal", "collision", "offroad", "timeout")
            assert info["is_success"] == (info["outcome"] == "goal")
            assert info["TimeLimit.truncated"] == (info["outcome"] == "timeout")
            assert info["terminal_observation"].shape == obs.shape[1:]
            saw_done = True
            saw_timeout |= info["outcome"] == "timeout"
        for i in np.flatnonzero(~done):
            assert "terminal_observation" not in infos[i]
        prev_active = active
    assert saw_done and saw_timeout
    # every world was reset by the timeout: its step counter restarted
    assert int(env.sim.step_count.max()) < STEPS


def test_world_reset_after_timeout_gives_active_slots(env):
    env.seed(2)
    env.reset()
    zeros = np.full(env.num_envs, 7, np.int64)  # zero jerk
    timed_out_worlds = set()
    for _ in range(STEPS):
        before = env.sim.step_count.cpu().numpy().copy()
        obs, _, done, infos = env.step(zeros)
        for i in np.flatnonzero(done):
            if infos[i]["outcome"] == "timeout":
                assert infos[i]["TimeLimit.truncated"]
                w = i // A
                # only a world at its horizon times agents out, and it restarts at once
                assert before[w] == STEPS - 1
                assert int(env.sim.step_count[w]) == 0
                assert env.active_mask().reshape(W, A)[w].any()
                assert np.any(obs[w * A:(w + 1) * A] != 0)
                timed_out_worlds.add(w)
    assert timed_out_worlds


def test_timeout_terminal_ends_timeouts_without_truncation(scenarios):
    """timeout_terminal=True: the same timeouts, reported as terminal (no TimeLimit.truncated),
    so SB3 does not bootstrap them; other outcomes unchanged."""
    from cpsim.envs.selfplay import SelfPlayVecEnv

    outcomes = {}
    for terminal in (False, True):
        e = SelfPlayVecEnv(scenarios, num_worlds=W, max_agents=A, seed=3, episode_steps=STEPS,
                           timeout_terminal=terminal)
        e.reset()
        seen = []
        for _ in range(STEPS):
            _, _, done, infos = e.step(np.full(e.num_envs, 7, np.int64))
            seen += [(i, infos[i]["outcome"], infos[i]["TimeLimit.truncated"]) for i in np.flatnonzero(done)
                     if "outcome" in infos[i]]
        e.close()
        outcomes[terminal] = seen
    assert [s[:2] for s in outcomes[False]] == [s[:2] for s in outcomes[True]]
    assert any(o == "timeout" and t for _, o, t in outcomes[False])
    assert not any(t for _, _, t in outcomes[True])
    with pytest.raises(ValueError, match="timeout_terminal"):
        SelfPlayVecEnv(scenarios, num_worlds=W, max_agents=A, timeout_terminal="yes")


def test_eval_task_share_sets_task_fields_only(scenarios):
    """eval_task_share: that share of agents gets the evaluation criterion's task fields
    (2 m, 30 m/s), the rest keep p_train draws; style fields stay p_train draws for all."""
    from cpsim.conditions import STYLE_MASK, TRAIN_HIGH, TRAIN_LOW, criterion_task_fields
    from cpsim.envs.selfplay import SelfPlayVecEnv

    task = ~STYLE_MASK
    for share, lo, hi in ((0.0, 0.0, 0.02), (0.5, 0.3, 0.7), (1.0, 1.0, 1.0)):
        e = SelfPlayVecEnv(scenarios, num_worlds=16, max_agents=A, seed=5, episode_steps=STEPS,
                           eval_task_share=share)
        e.reset()
        cond = np.asarray(e.sim.conditions.numpy() if hasattr(e.sim.conditions, "numpy") else e.sim.conditions)
        e.close()
        at_eval = np.all(np.isclose(cond[..., task], criterion_task_fields()), axis=-1)
        assert lo <= at_eval.mean() <= hi, (share, at_eval.mean())
        style = cond[..., STYLE_MASK]
        assert np.all(style >= TRAIN_LOW[STYLE_MASK] - 1e-6) and np.all(style <= TRAIN_HIGH[STYLE_MASK] + 1e-6)
        assert style.std(axis=(0, 1)).min() > 0  # still drawn, not fixed
    for bad in (-0.1, 1.5, "half"):
        with pytest.raises(ValueError, match="eval_task_share"):
            SelfPlayVecEnv(scenarios, num_worlds=W, max_agents=A, eval_task_share=bad)
    with pytest.raises(ValueError, match="eval_task_share"):
        SelfPlayVecEnv(scenarios, num_worlds=W, max_agents=A, condition="normal", eval_task_share=0.5)


def test_panel_share_sets_style_fields_only(scenarios):
    """panel_share: that share of agents drives under a panel profile's style fields exactly,
    the rest keep p_train styles; task fields stay p_train draws for every agent."""
    from cpsim.conditions import PANEL, PROFILES, STYLE_MASK, TRAIN_HIGH, TRAIN_LOW
    from cpsim.envs.selfplay import SelfPlayVecEnv

    panel_styles = np.stack([PROFILES[name][STYLE_MASK] for name in PANEL])  # (5, 8)
    for share, lo, hi in ((0.0, 0.0, 0.0), (0.5, 0.3, 0.7), (1.0, 1.0, 1.0)):
        e = SelfPlayVecEnv(scenarios, num_worlds=16, max_agents=A, seed=5, episode_steps=STEPS,
                           panel_share=share)
        e.reset()
        cond = np.asarray(e.sim.conditions.numpy() if hasattr(e.sim.conditions, "numpy") else e.sim.conditions)
        e.close()
        style = cond[..., STYLE_MASK].reshape(-1, 1, int(STYLE_MASK.sum()))
        which = np.all(np.isclose(style, panel_styles[None]), axis=-1)  # (W*A, 5)
        on_panel = which.any(axis=-1)
        assert lo <= on_panel.mean() <= hi, (share, on_panel.mean())
        if share == 1.0:  # every profile is drawn, not only one
            assert np.all(which.sum(axis=0) > 0)
        task = cond[..., ~STYLE_MASK]
        assert np.all(task >= TRAIN_LOW[~STYLE_MASK] - 1e-6) and np.all(task <= TRAIN_HIGH[~STYLE_MASK] + 1e-6)
        assert task.std(axis=(0, 1)).min() > 0  # task fields still drawn
    for bad in (-0.1, 1.5, None):
        with pytest.raises(ValueError, match="panel_share"):
            SelfPlayVecEnv(scenarios, num_worlds=W, max_agents=A, panel_share=bad)
    with pytest.raises(ValueError, match="panel_share"):
        SelfPlayVecEnv(scenarios, num_worlds=W, max_agents=A, condition="aggressive", panel_share=0.5)


def test_seed_makes_resets_reproducible(env):
    env.seed(11)
    a = env.reset()
    env.seed(11)
    b = env.reset()
    np.testing.assert_array_equal(a, b)


def test_bad_actions(env):
    env.reset()
    bad = np.zeros(env.num_envs, np.int64)
    bad[np.flatnonzero(env.active_mask())[0]] = 12
    with pytest.raises(ValueError, match="outside the action space"):
        env.step(bad)
    with pytest.raises(ValueError, match="expected"):
        env.step(np.zeros(3, np.int64))


def test_bad_construction(scenarios):
    from cpsim.envs.selfplay import SelfPlayVecEnv

    with pytest.raises(ValueError, match="profile"):
        SelfPlayVecEnv(scenarios, num_worlds=1, max_agents=2, condition="sporty")
    with pytest.raises(ValueError, match="unknown key"):
        SelfPlayVecEnv(scenarios, num_worlds=1, max_agents=2, not_a_setting=3)
    with pytest.raises(ValueError, match="family"):
        SelfPlayVecEnv(family="highway", num_worlds=1, max_agents=2)
    with pytest.raises(ValueError, match="seed: must be a whole number >= 0"):
        SelfPlayVecEnv(scenarios, num_worlds=1, max_agents=2, seed=-1)
    with pytest.raises(ValueError, match="render_worlds"):
        SelfPlayVecEnv(scenarios, num_worlds=1, max_agents=2, render_mode="rgb_array", render_worlds=0)


def test_argument_check_accepts_every_constructor_argument():
    import inspect

    from cpsim.envs.selfplay import SelfPlayVecEnv, check_selfplay_arguments

    checked = set(inspect.signature(check_selfplay_arguments).parameters) - {"config_overrides"}
    taken = set(inspect.signature(SelfPlayVecEnv.__init__).parameters) - {"self", "config_overrides"}
    assert checked == taken  # a recipe or grid may set any of them
    check_selfplay_arguments(seed=3, device="cpu", render_worlds=2, condition="normal", episode_steps=20)
    with pytest.raises(ValueError, match="panel_share: only applies to condition='train'"):
        check_selfplay_arguments(condition="normal", panel_share=0.5)


def test_fixed_condition_is_applied(scenarios):
    from cpsim.conditions import profile
    from cpsim.envs.selfplay import SelfPlayVecEnv

    e = SelfPlayVecEnv(scenarios, num_worlds=1, max_agents=3, condition="cautious", episode_steps=STEPS)
    e.reset()
    cond = e.sim.conditions.cpu().numpy()[0]
    present = e.sim.agent_index.cpu().numpy()[0] >= 0
    np.testing.assert_allclose(cond[present], np.broadcast_to(profile("cautious"), cond[present].shape))


def test_ppo_and_recurrent_ppo_learn_under_wrappers(env):
    from sb3_contrib import RecurrentPPO
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    wrapped = VecNormalize(VecMonitor(env), norm_reward=True)
    model = PPO("MlpPolicy", wrapped, n_steps=16, batch_size=96, n_epochs=1, seed=0, device="cpu",
                policy_kwargs=dict(net_arch=[32]))
    model.learn(total_timesteps=2 * 16 * env.num_envs)
    assert model.num_timesteps >= 2 * 16 * env.num_envs
    ep_info = list(model.ep_info_buffer)
    assert ep_info and all(np.isfinite(e["r"]) for e in ep_info)

    rmodel = RecurrentPPO("MlpLstmPolicy", env, n_steps=16, batch_size=96, n_epochs=1, seed=0, device="cpu",
                          policy_kwargs=dict(lstm_hidden_size=16, net_arch=[16]))
    rmodel.learn(total_timesteps=16 * env.num_envs)
    assert rmodel.num_timesteps >= 16 * env.num_envs


def test_render_tiles_worlds(scenarios):
    from cpsim.envs.selfplay import SelfPlayVecEnv

    e = SelfPlayVecEnv(scenarios, num_worlds=2, max_agents=3, render_mode="rgb_array", episode_steps=STEPS)
    e.reset()
    img = e.render()
    assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 5


def _cuda_ready() -> bool:
    import torch
    import warp as wp

    wp.init()
    return torch.cuda.is_available() and wp.get_cuda_device_count() > 0


@pytest.mark.cuda
def test_cuda_vecenv_returns_host_copies(scenarios):
    if not _cuda_ready():
        pytest.skip("needs a CUDA device (Warp and torch)")
    from cpsim.envs.selfplay import SelfPlayVecEnv

    e = SelfPlayVecEnv(scenarios, num_worlds=2, max_agents=4, device="cuda", episode_steps=STEPS)
    obs = e.reset()
    assert isinstance(obs, np.ndarray) and obs.dtype == np.float32
    obs2, rew, done, infos = e.step(np.full(e.num_envs, 7))
    assert isinstance(rew, np.ndarray) and rew.dtype == np.float32 and done.dtype == bool
    np.testing.assert_array_equal(e.active_mask(), e.sim.policy_mask.cpu().numpy().reshape(-1))


def test_empty_slots_end_episodes_so_evaluate_policy_finishes(scenarios):
    """max_agents above the controllable cars (the README's 16): slots that never hold an
    agent end an empty episode at each world reset, so SB3's evaluate_policy (and
    EvalCallback, which calls it) finishes instead of waiting forever on them."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.vec_env import VecMonitor

    from cpsim.envs.selfplay import SelfPlayVecEnv

    env = SelfPlayVecEnv(scenarios, num_worlds=2, max_agents=16, seed=0, episode_steps=STEPS)
    env.reset()
    never = ~env.active_mask()
    assert never.any()  # the pool has fewer than 16 controllable cars per scenario
    model = PPO("MlpPolicy", env, n_steps=8, batch_size=64, seed=0, device="cpu", policy_kwargs=dict(net_arch=[8]))
    for venv in (env, VecMonitor(env)):
        rewards, lengths = evaluate_policy(model, venv, n_eval_episodes=2 * env.num_envs, return_episode_rewards=True,
                                           warn=False)
        # an episode's length includes the inactive steps before it (after the slot's last one)
        assert len(rewards) == 2 * env.num_envs and max(lengths) < 2 * STEPS
    # the empty episodes: at the world reset, reward 0, no outcome, not a timeout
    env.seed(1)
    env.reset()
    held = env.active_mask()
    for _ in range(STEPS):
        _, rew, done, infos = env.step(np.full(env.num_envs, 7))
        held |= env.active_mask() & ~done
    empty = [i for i in np.flatnonzero(done) if infos[i].get("empty")]
    assert empty and all(not held[i] for i in empty)
    for i in empty:
        assert rew[i] == 0 and "outcome" not in infos[i] and infos[i]["TimeLimit.truncated"] is False
        assert not infos[i]["terminal_observation"].any()


def test_selfplay_vecnormalize_counts_active_slots_only(scenarios):
    """SelfPlayVecNormalize: observation statistics from active slots, zero observations on
    inactive ones (SB3's VecNormalize averages the padding's zeros in)."""
    from stable_baselines3.common.vec_env import VecNormalize

    from cpsim.envs.selfplay import SelfPlayVecEnv, SelfPlayVecNormalize

    env = SelfPlayVecEnv(scenarios, num_worlds=2, max_agents=16, seed=0, episode_steps=STEPS)
    ours, plain = SelfPlayVecNormalize(env), VecNormalize(env)
    obs = ours.reset()
    raw = ours.get_original_obs()
    active = env.active_mask()
    assert np.all(obs[~active] == 0) and ours.obs_rms.count == pytest.approx(active.sum() + 1e-4)
    np.testing.assert_allclose(ours.obs_rms.mean, raw[active].mean(0), atol=1e-5)
    plain.reset()
    assert plain.obs_rms.count == pytest.approx(env.num_envs + 1e-4)
    counted = ours.obs_rms.count
    for _ in range(3):
        obs, _, done, infos = ours.step(np.full(env.num_envs, 7))
        now = env.active_mask()
        counted += now.sum()
        assert np.all(obs[~now] == 0)
    assert ours.obs_rms.count == pytest.approx(counted)


def test_human_render_mode_runs_headless(scenarios):
    import matplotlib

    from cpsim.envs.selfplay import SelfPlayVecEnv

    matplotlib.use("Agg")
    e = SelfPlayVecEnv(scenarios, num_worlds=2, max_agents=3, render_mode="human", episode_steps=STEPS)
    e.reset()
    assert e.render() is None
    frame = e._viewer._image.get_array()
    assert frame.shape[:2] == (320, 640)  # two 320-pixel worlds side by side
    e.close()

