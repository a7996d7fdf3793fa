"""CounterPlay on the real simulator: replay, searches, budget cap, verification, save/load."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch as th

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from stable_baselines3.common.callbacks import BaseCallback  # noqa: E402
from stable_baselines3.common.logger import configure  # noqa: E402

import cpalgo.counterplay.driver as driver_module  # noqa: E402
from cpalgo import CounterPlay  # noqa: E402
from cpalgo.counterplay.driver import OWN_CONDITION  # noqa: E402
from cpsim import SelfPlayVecEnv  # noqa: E402

EPISODE = 40
POLICY = dict(lstm_hidden_size=16, net_arch=[32])


pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def make_env(seed: int = 0, device: str = "cpu") -> SelfPlayVecEnv:
    return SelfPlayVecEnv(num_worlds=2, max_agents=4, num_scenarios=4, seed=seed, device=device,
                          episode_steps=EPISODE, num_partners=4, num_road=16)


def make_model(env, device: str = "cpu", **kw) -> CounterPlay:
    args = dict(n_steps=EPISODE, batch_size=64, n_epochs=1, seed=0, device=device, policy_kwargs=POLICY)
    args.update(kw)
    return CounterPlay("MlpLstmPolicy", env, **args)


class RecordPositions(BaseCallback):
    """Keeps xy (W, A, 2) per world decision of the first episode of each world."""

    def __init__(self) -> None:
        super().__init__()
        self.xy: dict[tuple[int, int], np.ndarray] = {}

    def _grab(self) -> None:
        sim = self.training_env.sim
        steps = sim.step_count.cpu().numpy()
        xy = sim.xy.cpu().numpy()
        for w, t in enumerate(steps.tolist()):
            self.xy.setdefault((w, t), xy[w].copy())

    def _on_rollout_start(self) -> None:
        self._grab()

    def _on_step(self) -> bool:
        self._grab()
        return True


CUDA = pytest.param("cuda", marks=[pytest.mark.cuda,
                                   pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")])


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_factual_replay_with_main_draws_reproduces_the_rollout(device):
    env = make_env(device=device)
    model = make_model(env, device=device, max_searches=0)
    rec = RecordPositions()
    n = 20
    _, callback = model._setup_learn(n * env.num_envs, rec)
    callback.on_training_start(locals(), globals())
    first_episode = model._driver.roots.episode.copy()
    assert model.collect_rollouts(env, callback, model.rollout_buffer, n_rollout_steps=n)
    roots = model._driver.roots
    worlds = np.flatnonzero(roots.episode == first_episode)
    assert worlds.size, "every world reset during 20 decisions: the test needs a longer episode"
    w = int(worlds[0])
    steps, _ = roots.roots_of(w)
    assert sorted(steps.tolist()) == [0, 5, 10, 15]
    root = 5
    result = model.replay_root(w, root)
    replayed = result.actions[0]  # (T, A), -1 where an agent did not decide
    recorded = roots.actions[w].T[root:n]  # (n - root, A)
    deciding = replayed[: n - root] >= 0
    assert deciding.any()
    np.testing.assert_array_equal(replayed[: n - root][deciding], recorded[deciding])
    for t in range(root, n + 1):
        np.testing.assert_array_equal(result.xy[0, t - root], rec.xy[(w, t)], err_msg=f"decision {t}")
    # fresh draws instead of the main ones give another trajectory (the check can fail)
    other = model.replay_root(w, root, main_draws=False)
    assert not np.array_equal(other.actions[0][: n - root], result.actions[0][: n - root])


def test_branch_rewards_are_clamped_as_the_rollouts_are():
    """With ``clip_reward`` a branch's focal rewards (selection by return, PPO on recoveries)
    are the learner's clamped rewards: a replay of the rollout gets the buffer's rewards."""
    env = make_env()
    c = 0.01
    model = make_model(env, max_searches=0, clip_reward=c)
    n = 20
    _, callback = model._setup_learn(n * env.num_envs, None)
    callback.on_training_start(locals(), globals())
    first_episode = model._driver.roots.episode.copy()
    assert model.collect_rollouts(env, callback, model.rollout_buffer, n_rollout_steps=n)
    w = int(np.flatnonzero(model._driver.roots.episode == first_episode)[0])
    root = 5
    result = model.replay_root(w, root)
    alive = result.focal_alive[0, : n - root].numpy()
    assert alive.any()
    replayed = result.focal_rewards[0, : n - root].numpy()[alive]
    recorded = model.rollout_buffer.rewards[root:n, w * env.max_agents][alive]
    np.testing.assert_allclose(replayed, recorded, atol=1e-7)
    assert np.abs(replayed).max() == pytest.approx(c)  # the clamp bites


def test_searches_respect_the_branch_cap_and_are_logged(tmp_path):
    env = make_env(1)
    model = make_model(env, branch_cap=3.0, verify=True)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    for _ in range(3):  # the searches of generation g run during generation g+1
        model.learn(1, reset_num_timesteps=False)
    b = model.budget
    assert b.generations == 3
    assert b.history[0]["branch"] == 0  # nothing to search before the first rollout ends
    for gen in b.history:
        assert gen["branch"] <= 3.0 * gen["cap_main"]
    assert b.factual > 0 and b.candidate > 0, "no search ran: no failure with a root in the window"
    assert b.candidate >= 4 * b.factual  # five candidates per factual branch, similar lengths
    assert b.total == b.main + b.factual + b.candidate + b.verification
    with open(tmp_path / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3
    for key in ("failures", "searches", "searches_skipped", "admissible", "verified_teachers",
                "verification_pass_rate", "branch_share", "budget_total", "profile/cautious", "root_depth_mean"):
        assert f"counterplay/{key}" in rows[0], key
    searches = sum(float(r["counterplay/searches"]) for r in rows)
    assert searches > 0
    # one verdict per retry (five candidates per search)
    verdicts = {v: sum(float(r[f"counterplay/retries_{v}"]) for r in rows)
                for v in ("incomplete", "not_better", "harms_other", "admitted")}
    assert sum(verdicts.values()) == 5 * searches
    assert float(rows[-1]["counterplay/budget_total"]) == b.total
    depth_columns = [k for k in rows[0] if k.startswith("counterplay/roots_by_depth/")]
    assert sum(float(r[k] or 0) for r in rows for k in depth_columns) == searches
    assert model.num_timesteps == b.total  # learn counts B_post, branches included


def test_default_cap_skips_searches_it_cannot_afford():
    env = make_env(1)
    model = make_model(env, branch_cap=0.01)
    model.learn(1)
    first = model.search_stats
    assert first.failures > 0 and first.searches == 0
    model.learn(1, reset_num_timesteps=False)  # generation 1's searches come up in generation 2
    assert model.budget.branch == 0
    second = model.search_stats
    assert second.searches_skipped == first.failures - first.failures_without_root


def _force_teachers(monkeypatch, verified: bool) -> None:
    # a random policy rarely completes a task, so pick the first candidate as the teacher
    # and decide the verification: what is tested is the pipeline around them
    monkeypatch.setattr(driver_module, "choose_teacher", lambda factual, candidates, selection: 0)
    monkeypatch.setattr(driver_module, "verify", lambda factual, candidate: verified)


def two_generations(model) -> None:
    """Rollout 1 records failures; rollout 2 searches them; update 2 distils them."""
    model.learn(1)
    model.learn(1, reset_num_timesteps=False)


def test_failed_verification_discards_the_search(monkeypatch):
    _force_teachers(monkeypatch, verified=False)
    env = make_env(1)
    model = make_model(env, branch_cap=3.0)
    two_generations(model)
    stats = model.search_stats
    assert stats.teachers_chosen > 0
    assert stats.verification_failed == stats.teachers_chosen
    assert stats.teachers == 0 and model.budget.verification > 0


def test_verified_teachers_are_distilled(monkeypatch):
    _force_teachers(monkeypatch, verified=True)
    env = make_env(1)
    model = make_model(env, branch_cap=3.0)
    seen: list[int] = []
    original = model._prepare_distillation

    def spy():
        batch = original()
        if batch is not None:
            seen.append(batch.num_teachers)
            # the student sees the deployment condition, the teacher saw the panel profile
            obs = batch.student_obs.reshape(batch.num_teachers, -1, batch.student_obs.shape[-1])
            layout = env.obs_layout
            assert not th.allclose(obs[0, 0, layout.condition], model._teachers[0].obs[0, layout.condition])
        return batch

    model._prepare_distillation = spy
    model.learn(1)
    assert not seen  # generation 1's failures are searched during generation 2
    model.learn(1, reset_num_timesteps=False)
    assert seen and seen[0] == model.search_stats.teachers > 0
    assert np.isfinite(model.logger.name_to_value.get("counterplay/distill_kl", 0.0))


def test_save_load_continue_with_branching(tmp_path):
    env = make_env(2)
    model = make_model(env, branch_cap=3.0).learn(1)
    model.save(tmp_path / "cp")
    loaded = CounterPlay.load(tmp_path / "cp.zip", env=env, device="cpu")
    assert loaded.counterfactual and loaded.branch_cap == 3.0
    assert loaded.budget.total == model.budget.total
    loaded.learn(1, reset_num_timesteps=False)
    assert loaded.budget.generations == 2 and loaded.budget.main > model.budget.main


@pytest.mark.parametrize(
    "ablation",
    [
        dict(backtrack="fixed", fixed_depth=10, shared_randomness=False),
        dict(style_change=False, selection="return", verify=False, distill="ppo"),
    ],
)
def test_ablations_run_end_to_end(monkeypatch, ablation):
    _force_teachers(monkeypatch, verified=True)
    env = make_env(1)
    model = make_model(env, branch_cap=3.0, **ablation)
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    two_generations(model)
    stats = model.search_stats
    assert stats.searches > 0 and model.budget.candidate > 0
    if ablation.get("verify") is False:
        assert model.budget.verification == 0
    else:
        assert model.budget.verification > 0
    if ablation.get("backtrack") == "fixed":
        depths = list(stats.root_depths)
        assert depths and all(abs(d - 10) <= 2 for d in depths)  # roots every 5 decisions
    assert stats.teachers > 0
    # teachers are counted by the style they drove: none without a style change
    assert sum(stats.profiles.values()) == stats.teachers
    if ablation.get("style_change") is False:
        assert set(stats.profiles) == {OWN_CONDITION}
    else:
        assert set(stats.profiles) <= set(model.panel)
    after = model.policy.state_dict()
    assert not all(th.equal(before[k], after[k]) for k in before)


def test_roots_belong_to_their_generation_and_searches_use_the_frozen_policy():
    env = make_env(1)
    model = make_model(env, branch_cap=3.0, root_lifetime="generation")
    model.learn(1)
    driver = model._driver
    assert driver.has_pending, "generation 1 queued no search"
    frozen = {k: v.clone() for k, v in driver._frozen.state_dict().items()}
    after_update = model.policy.state_dict()
    # the searches of generation 1 run under the policy of rollout 1, not the updated one
    assert not all(th.equal(frozen[k], after_update[k]) for k in frozen)
    start = model._rollout_start

    def check_start(env_):
        start(env_)
        roots = driver.roots
        assert (roots.root_step < 0).all(), "a root of generation 1 survived into generation 2"
        assert all(roots.roots_of(w)[0].size == 0 for w in range(roots.num_worlds))

    model._rollout_start = check_start
    runner, used = driver.runner, []
    run = runner.run

    def spy(jobs):
        used.append(all(th.equal(frozen[k], v) for k, v in runner.policy.state_dict().items()))
        return run(jobs)

    runner.run = spy
    model.learn(1, reset_num_timesteps=False)
    assert model.search_stats.searches > 0
    assert used and all(used)


def test_roots_outlive_their_generation_while_their_episode_runs():
    """root_lifetime="episode" (default): a rollout shorter than the episode leaves every
    world mid-episode, and the next rollout can still backtrack to all of that episode's
    roots; "generation" drops them (previous test)."""
    env = make_env(1)
    n_steps = 30  # < EPISODE: each episode spans two rollouts
    model = make_model(env, branch_cap=3.0, n_steps=n_steps)
    assert model.root_lifetime == "episode"
    model.learn(1)
    driver = model._driver
    start = model._rollout_start
    seen = []

    def check_start(env_):
        start(env_)
        roots = driver.roots
        steps_now = np.asarray(env.sim.step_count.numpy() if hasattr(env.sim.step_count, "numpy")
                               else env.sim.step_count)
        for w in range(roots.num_worlds):
            kept = np.sort(roots.roots_of(w)[0])
            # every root decision of the running episode so far (interval 5), none of an older one
            expected = np.arange(0, steps_now[w], 5)
            assert np.array_equal(kept, expected[-roots.ring:]), (w, kept, steps_now[w])
            seen.append(kept.size)

    model._rollout_start = check_start
    model.learn(1, reset_num_timesteps=False)
    assert seen and max(seen) > 0, "no root of generation 1 was usable in generation 2"
    with pytest.raises(ValueError, match="root_lifetime"):
        make_model(make_env(1), root_lifetime="forever")


def test_a_checkpoint_older_than_root_lifetime_comes_back_with_the_behaviour_it_had(tmp_path):
    """Checkpoints written before the setting existed dropped roots every generation: load
    (and a grid resume through apply_legacy_settings) restores that, today's saves keep theirs."""
    import io
    import json
    import zipfile

    env = make_env(1)
    model = make_model(env)
    new = tmp_path / "new.zip"
    model.save(new)
    old = tmp_path / "old.zip"
    with zipfile.ZipFile(new) as src, zipfile.ZipFile(old, "w") as dst:
        for item in src.infolist():
            payload = src.read(item.filename)
            if item.filename == "data":
                data = json.loads(payload)
                assert data.pop("root_lifetime") == "episode"
                payload = json.dumps(data).encode()
            dst.writestr(item, payload)
    assert CounterPlay.load(new, env=env).root_lifetime == "episode"
    assert CounterPlay.load(old, env=env).root_lifetime == "generation"
    assert CounterPlay.load(old, env=env, root_lifetime="episode").root_lifetime == "episode"
    assert CounterPlay.load(io.BytesIO(old.read_bytes()), env=env).root_lifetime == "generation"  # in memory too
    fresh = make_model(env)
    fresh.set_parameters(str(old), exact_match=True)
    fresh.apply_legacy_settings(str(old))
    assert fresh.root_lifetime == "generation" and fresh._search_settings().root_lifetime == "generation"


def test_learn_counts_b_post_and_the_progress_bar_ends_at_what_ran(capsys):
    env = make_env(1)
    model = make_model(env, branch_cap=3.0)
    per_generation_main = None
    model.learn(3 * EPISODE, progress_bar=True)
    b = model.budget
    per_generation_main = b.history[0]["main"]
    assert model.num_timesteps == b.total
    # stops at the first generation boundary at or past the target
    assert b.total >= 3 * EPISODE and b.total - b.history[-1]["main"] - b.history[-1]["branch"] < 3 * EPISODE
    assert per_generation_main < EPISODE * env.num_envs  # inactive slots do not count
    err = capsys.readouterr().err
    assert f"{b.total}/{b.total}" in err.replace(",", "") or "100%" in err
