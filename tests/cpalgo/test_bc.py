"""Behaviour-cloning traffic model: training, checkpoint format, co-player interface."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th

from cpalgo.traffic.bc import BCData, BCPolicy, TrainConfig, train

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def _synthetic(n: int = 3000, d: int = 24, k: int = 12, seed: int = 0) -> BCData:
    """Labels are a deterministic function of a few features (learnable), plus a
    condition slice (features 4..8) filled with noise the model must ignore."""
    rng = np.random.default_rng(seed)
    obs = rng.uniform(-1, 1, (n, d)).astype(np.float32)
    actions = (np.digitize(obs[:, 0], [-0.5, 0.0, 0.5]) * 3 + np.digitize(obs[:, 1], [-0.33, 0.33])).astype(np.int64)
    assert actions.max() < k
    return BCData(obs, actions, np.zeros(n, np.float32), rng.integers(0, 40, n))


def test_train_learns_and_beats_majority():
    data = _synthetic()
    model, m = train(data, 12, condition_slice=(4, 8), config=TrainConfig(epochs=15, hidden=(64,), batch_size=64, lr=5e-3))
    assert m["val_accuracy"] > 0.85
    assert m["val_accuracy"] > m["val_majority_accuracy"] + 0.4
    assert m["train_samples"] + m["val_samples"] == 3000


def test_condition_slice_is_ignored_and_predict_is_sb3_compatible():
    model = BCPolicy(24, 12, (32,), condition_slice=(4, 8))
    obs = np.random.default_rng(1).uniform(-1, 1, (5, 24)).astype(np.float32)
    other = obs.copy()
    other[:, 4:8] = 9.0
    a, state = model.predict(obs, state=None, episode_start=np.ones(5, bool), deterministic=True)
    b, _ = model.predict(other, None, None, True)
    assert state is None and a.dtype == np.int64 and a.shape == (5,)
    np.testing.assert_array_equal(a, b)
    with th.no_grad():
        np.testing.assert_array_equal(a, model(th.as_tensor(obs)).argmax(-1).numpy())


def test_save_load_roundtrip_small(tmp_path):
    data = _synthetic(800)
    model, _ = train(data, 12, (4, 8), TrainConfig(epochs=2, hidden=(128, 128)))
    path = model.save(tmp_path / "bc.pt")
    assert path.stat().st_size < 1_000_000
    loaded = BCPolicy.load(path)
    assert (loaded.obs_size, loaded.num_actions, loaded.condition_slice) == (24, 12, (4, 8))
    a, _ = model.predict(data.obs[:200])
    b, _ = loaded.predict(data.obs[:200])
    assert (a == b).mean() > 0.97  # float16 storage may flip a near-tie
    assert [p.name for p in tmp_path.iterdir()] == ["bc.pt"]


def test_load_rejects_bad_files(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        BCPolicy.load(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="bad.pt"):
        BCPolicy.load(bad)
    th.save({"format": "something-else"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a cpalgo.bc"):
        BCPolicy.load(tmp_path / "other.pt")


def test_train_config_rejects_unknown_keys():
    with pytest.raises(ValueError, match="unknown keys"):
        TrainConfig.from_dict({"epochz": 3})


def test_collect_labels_reproduce_the_logs():
    """On log replay, the labelled action held for 0.5 s lands close to the logged state
    (the probe simulator really starts from each agent's current state)."""
    pytest.importorskip("cpsim.simulator")
    from cpalgo.traffic.bc import collect
    from cpsim.scenario import train_pool

    scenarios = list(train_pool(2, 0))
    replay = collect(scenarios, num_worlds=2, max_agents=12, lookahead=5, mode="replay")
    n_ctrl = sum(int(s.controllable.sum()) for s in scenarios)
    assert replay.obs.shape[0] == replay.actions.shape[0] > 20 * min(n_ctrl, 12)
    assert replay.actions.min() >= 0 and replay.actions.max() < 12
    assert np.median(replay.error_m) < 0.05 and np.mean(replay.error_m) < 0.3
    assert np.unique(replay.actions).size >= 3  # not one constant label
    assert set(np.unique(replay.scenario)) == {0, 1}
    # driving with the labels themselves (no noise) stays on the logs: the labels are a
    # working log-tracking controller, so the corrective samples of 'track' are meaningful
    track = collect(scenarios, num_worlds=2, max_agents=12, lookahead=5, mode="track", noise=0.0)
    assert np.median(track.error_m) < 0.3
    with pytest.raises(ValueError, match="mode"):
        collect(scenarios, mode="dagger")


# ---------------------------------------------------------------- DAgger (tiny settings)
class _Constant:
    """A stand-in learner that always takes one action (hard braking when 0)."""

    def __init__(self, action: int):
        self.action = action
        self.calls = 0

    def predict(self, obs, state=None, episode_start=None, deterministic=True):
        self.calls += 1
        return np.full(len(obs), self.action, np.int64), None


@pytest.fixture(scope="module")
def tiny_pool():
    pytest.importorskip("cpsim.simulator")
    from cpsim.scenario import train_pool

    return list(train_pool(3, 0))


def test_rollouts_relabel_the_learner_states_with_the_tracking_expert(tiny_pool):
    from cpalgo.traffic.bc import traffic_rollouts
    from cpsim.config import JERK_LAT, JERK_LONG

    kw = dict(num_worlds=3, max_agents=16, seed=0, ego_replay=0.0)
    expert, s_e = traffic_rollouts(tiny_pool, None, 1.0, **kw)
    n_task = sum(int(s.controllable.sum()) for s in tiny_pool)
    assert (s_e.learner_agents, s_e.expert_agents) == (0, n_task)
    assert s_e.expert_harm_rate <= 0.2  # the expert tracks collision-free logs
    assert expert.obs.dtype == np.float16 and expert.obs.shape[0] == expert.actions.size == s_e.samples
    assert np.unique(expert.actions).size >= 3
    # the targets head's rule turns the expert's target accelerations back into its actions
    from cpalgo.traffic.bc import targets_to_actions

    rebuilt = targets_to_actions(th.as_tensor(expert.targets), th.as_tensor(expert.obs.astype(np.float32)))
    assert (rebuilt.numpy() == expert.actions).mean() > 0.95
    # a learner that only brakes: every task vehicle is its own, the states it visits are
    # recorded, and their labels are the expert's (mostly "speed back up"), not its action
    brake = int(np.argmin(JERK_LONG)) * JERK_LAT.size + int(np.argmin(np.abs(JERK_LAT)))
    learner = _Constant(brake)
    data, s_l = traffic_rollouts(tiny_pool, learner, 0.0, **kw)
    assert learner.calls > 0 and (s_l.learner_agents, s_l.expert_agents) == (n_task, 0)
    assert (data.actions != brake).mean() > 0.5
    speed = np.abs(data.obs[:, 0].astype(np.float32)).mean()
    assert speed < np.abs(expert.obs[:, 0].astype(np.float32)).mean()  # off the expert's states
    assert set(np.unique(data.scenario)) <= {0, 1, 2}
    # keep subsamples; slot 0 replaying its log is no task vehicle of the learner
    sub, s_k = traffic_rollouts(tiny_pool, learner, 0.0, **{**kw, "ego_replay": 1.0}, keep=0.3)
    assert s_k.learner_agents <= n_task - len(tiny_pool) and sub.actions.size < 0.6 * data.actions.size
    with pytest.raises(ValueError, match="model"):
        traffic_rollouts(tiny_pool, None, 0.5, **kw)


def test_dagger_aggregates_rounds_and_checkpoints(tiny_pool, tmp_path):
    from cpalgo.traffic.bc import BCPolicy, DaggerConfig, aggregate, dagger

    a = BCData(np.ones((2, 3), np.float16), np.array([1, 2]), np.zeros(2, np.float32), np.array([0, 1]))
    b = BCData(np.zeros((1, 3), np.float16), np.array([3]), np.zeros(1, np.float32), np.array([2]))
    agg = aggregate([a, b])
    assert agg.obs.shape == (3, 3) and agg.actions.tolist() == [1, 2, 3]
    cfg = DaggerConfig(betas=(1.0, 0.0), first_epochs=1, round_epochs=1, num_worlds=3, max_agents=16, noise=0.1)
    model, history = dagger(tiny_pool, cfg, TrainConfig(hidden=(16,), val_fraction=0.0), checkpoint=tmp_path / "d.pt")
    assert [h["round"] for h in history] == [0, 1] and [h["beta"] for h in history] == [1.0, 0.0]
    assert history[0]["learner_agents"] == 0 and history[1]["expert_agents"] == 0
    assert history[1]["aggregate_samples"] == history[0]["samples"] + history[1]["samples"]
    saved = BCPolicy.load(tmp_path / "d.pt")
    assert saved.meta["dagger_round"] == 1 and len(saved.meta["dagger"]) == 2
    with pytest.raises(ValueError, match="betas"):
        DaggerConfig(betas=(0.5, 0.0))


def test_targets_head_regresses_and_acts_through_the_expert_rule(tmp_path):
    from cpalgo.traffic.bc import TARGET_SCALE, targets_to_actions

    data = _synthetic(1500, d=24)
    data.obs[:, 1:3] = 0.0  # own accelerations 0: the rule's choice depends on the targets only
    data.targets = np.stack([4.0 * data.obs[:, 5], 3.0 * data.obs[:, 6]], -1).astype(np.float32)
    data.actions = targets_to_actions(th.as_tensor(data.targets), th.as_tensor(data.obs)).numpy()
    model, m = train(data, 12, (8, 12), TrainConfig(epochs=20, hidden=(64,), batch_size=64, lr=5e-3, head="targets"))
    assert model.head == "targets" and m["val_accuracy"] > 0.8
    with th.no_grad():
        out = model.raw(th.as_tensor(data.obs[:300])) * th.as_tensor(TARGET_SCALE)
    assert np.abs(out.numpy() - data.targets[:300]).mean() < 0.3
    # forward gives action logits whatever the head (SPICED's reference reads them)
    with th.no_grad():
        logits = model(th.as_tensor(data.obs[:300]))
    assert logits.shape == (300, 12)
    np.testing.assert_array_equal(logits.argmax(-1).numpy(), model.predict(data.obs[:300])[0])
    # classic dynamics: the nearest acceleration command, straight ahead for no lateral target
    from cpsim.config import CLASSIC_ACCEL, CLASSIC_STEER

    obs = np.zeros((2, 24), np.float32)
    obs[:, 0], obs[:, 4] = 0.5, 0.45
    act = targets_to_actions(th.tensor([[1.2, 0.0], [-3.9, 0.0]]), th.as_tensor(obs), "classic").numpy()
    assert [CLASSIC_ACCEL[a // CLASSIC_STEER.size] for a in act] == [CLASSIC_ACCEL[4], CLASSIC_ACCEL[0]]
    assert all(CLASSIC_STEER[a % CLASSIC_STEER.size] == 0.0 for a in act)
    loaded = BCPolicy.load(model.save(tmp_path / "t.pt"))
    assert loaded.head == "targets" and (loaded.predict(data.obs[:300])[0] == model.predict(data.obs[:300])[0]).mean() > 0.97
    with pytest.raises(ValueError, match="targets"):
        train(BCData(data.obs, data.actions, data.error_m, data.scenario), 12, None, TrainConfig(head="targets"))
