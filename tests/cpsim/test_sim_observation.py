"""Observation layout: partners at known relative poses, road segments, condition slice."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import cpsim
from cpsim.config import Controller
from cpsim.observation import EGO_FEATURE_NAMES, ObsLayout
from tests.cpsim.scenes import LANE_WIDTH, agent, make_scenario

NORMAL = cpsim.profile("normal")


def place(sim, w, a, x, y, heading, speed):
    sim.xy[w, a] = torch.tensor([x, y])
    sim.heading[w, a] = heading
    sim.velocity[w, a] = torch.tensor([speed * math.cos(heading), speed * math.sin(heading)])
    sim.speed[w, a] = speed


def rot(v, h):
    c, s = math.cos(h), math.sin(h)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def test_layout_slices_and_sizes():
    lay = ObsLayout(num_partners=16, num_road=64)
    assert lay.ego == slice(0, 17) and lay.condition == slice(17, 27)
    assert lay.partners == slice(27, 27 + 160) and lay.road == slice(187, 187 + 512)
    assert lay.size == 699 and lay.ego_index("time_left") == 16
    big = ObsLayout(num_partners=63, num_road=200)
    assert big.size == 17 + 10 + 630 + 1600


def test_partner_at_known_relative_pose():
    sc = make_scenario([agent(100.0, 0.0, goal=(200.0, 0.0)),
                        agent(110.0, 2.0, length=5.0, width=2.2, goal=(200.0, 2.0)),
                        agent(95.0, 20.0, kind=cpsim.AgentType.CYCLIST, length=1.8, width=0.6),
                        agent(100.0, 60.0, goal=(200.0, 60.0))])
    sim = cpsim.Simulator([sc], num_worlds=2, max_agents=4, seed=0)
    sim.reset(conditions=NORMAL)
    w = 1
    slot = {int(i): s for s, i in enumerate(sim.agent_index[w].tolist())}
    assert slot[0] == 0 and slot[3] == 2 and slot[2] == 3  # controllable before the cyclist
    h0 = 0.3
    place(sim, w, 0, 100.0, 0.0, h0, 4.0)
    near = np.array([100.0, 0.0]) + rot((10.0, 2.0), h0)   # (10, 2) in the ego frame
    place(sim, w, slot[1], *near, h0 + 0.5, 6.0)
    far = np.array([100.0, 0.0]) + rot((-15.0, 20.0), h0)  # 25 m away, behind-left
    place(sim, w, slot[2], *far, h0 - 1.0, 0.0)
    place(sim, w, slot[3], 100.0, 60.0, 0.0, 0.0)         # 60 m: out of the 50 m range
    sim.refresh()
    parts = sim.obs_layout.split(sim.obs)["partners"][w, 0].numpy()
    rv = (6 * math.cos(0.5) - 4.0, 6 * math.sin(0.5))
    expect0 = [10 / 50, 2 / 50, math.cos(0.5), math.sin(0.5), rv[0] / 20, rv[1] / 20, 5.0 / 10, 2.2 / 5, 0, 1]
    np.testing.assert_allclose(parts[0], expect0, atol=1e-5)
    rv2 = rot((-4.0 * math.cos(h0), -4.0 * math.sin(h0)), -h0)  # the cyclist stands still
    expect1 = [-15 / 50, 20 / 50, math.cos(-1.0), math.sin(-1.0), rv2[0] / 20, rv2[1] / 20, 0.18, 0.6 / 5, 1, 1]
    np.testing.assert_allclose(parts[1], expect1, atol=1e-5)
    assert np.all(parts[2:] == 0)
    # world 0 is untouched by the edit of world 1 and its own obs is unchanged by refresh
    assert sim.obs_layout.split(sim.obs)["partners"][0, 0, :, -1].sum().item() == 2


def test_ego_features_condition_and_time_left():
    sc = make_scenario([agent(0.0, 0.5, speed=8.0, heading=0.1, goal=(60.0, 0.5))])
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=1, seed=0)
    sim.reset(conditions=NORMAL)
    ego = sim.obs[0, 0, sim.obs_layout.ego].numpy()
    f = dict(zip(EGO_FEATURE_NAMES, ego))
    assert f["speed"] == pytest.approx(8.0 / 20)
    assert f["length"] == pytest.approx(0.45) and f["width"] == pytest.approx(0.4)
    g = rot((60.0, 0.0), -0.1)
    assert f["goal_x"] == pytest.approx(g[0] / 100, abs=1e-5) and f["goal_y"] == pytest.approx(g[1] / 100, abs=1e-5)
    assert f["goal_dir_x"] == pytest.approx(math.cos(-0.1), abs=1e-5)
    assert f["goal_distance"] == pytest.approx(0.6, abs=1e-5)
    assert f["lane_offset"] == pytest.approx(0.5 / 4.0, abs=1e-5) and f["has_lane"] == 1.0
    assert f["lane_heading_error"] == pytest.approx(0.1 / math.pi, abs=1e-5)
    assert f["time_left"] == 1.0 and f["collided"] == 0.0
    np.testing.assert_allclose(sim.obs[0, 0, sim.obs_layout.condition].numpy(),
                               cpsim.normalize_condition(NORMAL), atol=1e-6)
    for _ in range(3):
        sim.step(np.full((1, 1), 7))
    assert sim.obs[0, 0, sim.obs_layout.ego_index("time_left")].item() == pytest.approx(1 - 3 / 91)


def test_road_segments_in_ego_frame():
    sc = make_scenario([agent(100.0, 0.0, goal=(200.0, 0.0))])
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=1, seed=0)
    sim.reset(conditions=NORMAL)
    road = sim.obs_layout.split(sim.obs)["road"][0, 0].numpy()
    present = road[:, 7] == 1
    # the 300 m polylines are cut into 10 m pieces; 50 m from the cell centre + half the
    # 5 m cell's diagonal, and the agent is within half a diagonal of the centre
    assert 40 <= present.sum() <= 64
    assert np.all(np.hypot(road[present, 0], road[present, 1]) <= (50 + 5 * 2 ** 0.5) / 50 + 1e-6)
    assert np.all(road[~present] == 0)
    lanes = road[present & (road[:, 5] == 1)]
    edges = road[present & (road[:, 6] == 1)]
    assert len(lanes) >= 18 and len(edges) >= 18
    # the lane piece from x = 100 to 110 on y = 0: midpoint (5, 0), direction (1, 0), 10 m
    hit = np.all(np.abs(lanes[:, :5] - [5 / 50, 0.0, 1.0, 0.0, 1.0]) < 1e-5, axis=1)
    assert hit.sum() == 1
    # an upper-edge piece: y = 5.55 m left of the ego
    assert np.any(np.abs(edges[:, 1] - (LANE_WIDTH * 1.5) / 50) < 1e-5)
    # nearest first (up to the grid cell size)
    d = np.hypot(road[present, 0], road[present, 1]) * 50
    assert d[0] < 8.0 and np.all(d[:5] < d[-5:].min())


def test_replace_condition_numpy_and_torch():
    lay = ObsLayout(num_partners=2, num_road=3)
    obs = np.random.default_rng(0).normal(size=(4, 5, lay.size)).astype(np.float32)
    cond = cpsim.profile("aggressive")
    out = lay.replace_condition(obs, cond)
    assert out is not obs and out.shape == obs.shape
    np.testing.assert_allclose(out[..., lay.condition], np.broadcast_to(cpsim.normalize_condition(cond), (4, 5, 10)))
    np.testing.assert_array_equal(out[..., lay.ego], obs[..., lay.ego])
    np.testing.assert_array_equal(out[..., lay.partners.start:], obs[..., lay.partners.start:])
    t = torch.as_tensor(obs)
    per_row = np.stack([cpsim.profile("cautious"), cond, cond, cond])[:, None, :]  # (4, 1, 10)
    tout = lay.replace_condition(t, per_row)
    assert isinstance(tout, torch.Tensor) and not torch.equal(tout, t)
    np.testing.assert_allclose(tout[0, :, lay.condition].numpy(),
                               np.broadcast_to(cpsim.normalize_condition(cpsim.profile("cautious")), (5, 10)),
                               atol=1e-6)
    with pytest.raises(ValueError, match="conditions_raw"):
        lay.replace_condition(obs, np.zeros(9))


def test_set_conditions_updates_condition_slice_only():
    sc = make_scenario([agent(0.0, 0.0, speed=5.0, goal=(60.0, 0.0))])
    sim = cpsim.Simulator([sc], num_worlds=2, max_agents=1, seed=0)
    sim.reset(conditions=NORMAL)
    before = sim.obs.clone()
    sim.set_conditions(cpsim.profile("cautious"), worlds=[1])
    lay = sim.obs_layout
    np.testing.assert_array_equal(sim.obs[0].numpy(), before[0].numpy())
    np.testing.assert_allclose(sim.obs[1, 0, lay.condition].numpy(),
                               cpsim.normalize_condition(cpsim.profile("cautious")), atol=1e-6)
    np.testing.assert_array_equal(sim.obs[1, 0, lay.ego].numpy(), before[1, 0, lay.ego].numpy())
    np.testing.assert_allclose(lay.replace_condition(before[1], cpsim.profile("cautious")).numpy(),
                               sim.obs[1].numpy(), atol=1e-6)
    assert sim.controllers[0, 0].item() == Controller.POLICY


def test_incremental_observation_equals_recomputed_from_scratch():
    # the step kernel only rewrites what changed (dead rows, stale entries, same-cell road
    # constants); a forced full recomputation must give exactly the same observation
    from tests.cpsim.scenes import small_pool

    sim = cpsim.Simulator(small_pool(3), num_worlds=6, max_agents=3, seed=0)
    rng = np.random.default_rng(0)
    for t in range(25):
        sim.step(rng.integers(0, 12, size=(6, 3)))
        if t % 5 == 4:
            incremental = sim.obs.clone()
            sim.refresh()
            np.testing.assert_array_equal(incremental.numpy(), sim.obs.numpy())
        done = sim.world_done.numpy()
        if done.any():
            sim.reset(worlds=np.flatnonzero(done))
    assert (sim.metrics["steps_alive"] > 0).any()


def test_scenery_agents_are_not_observed_unless_observe_all():
    sc = make_scenario([agent(0.0, 0.0, speed=5.0, goal=(80.0, 0.0)),
                        agent(10.0, LANE_WIDTH, speed=5.0, goal=(90.0, LANE_WIDTH)),   # task agent
                        agent(20.0, 0.0),                                              # parked car
                        agent(5.0, 8.0, kind=cpsim.AgentType.PEDESTRIAN, speed=1.0, goal=(5.0, 20.0))])
    for observe_all in (False, True):
        sim = cpsim.Simulator([sc], num_worlds=1, max_agents=4, seed=0, config={"observe_all": observe_all})
        sim.reset(conditions=NORMAL)
        sim.set_controllers(np.array([Controller.POLICY, Controller.REPLAY, Controller.REPLAY, Controller.REPLAY]))
        sim.step(np.full((1, 4), 7))
        assert sim.task_agent[0].tolist() == [True, True, False, False]
        rows = np.abs(sim.obs[0].numpy()).sum(1) > 0
        assert rows.tolist() == [True, True, observe_all, observe_all]
        # scenery is still visible to the others as partners
        assert sim.obs_layout.split(sim.obs)["partners"][0, 0, :, -1].sum().item() == 3
