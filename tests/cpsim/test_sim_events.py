"""Events: goal radius and speed, removal / stop / ignore rules, timeout, world_done, reward terms."""

from __future__ import annotations

import math

import numpy as np
import pytest

import cpsim
from cpsim.conditions import FIELD_INDEX
from cpsim.config import Controller, Outcome
from cpsim.kernels.reward import comfort_violations_np
from tests.cpsim.scenes import LANE_WIDTH, agent, make_scenario

NORMAL = cpsim.profile("normal")
KEEP_JERK = 2 * 3 + 1  # zero jerks: constant speed, straight


def cond(**fields):
    c = NORMAL.copy()
    for k, v in fields.items():
        c[FIELD_INDEX[k]] = v
    return c


def test_goal_radius_and_speed_threshold():
    # ego at 10 m/s (1 m per step) heads to a goal 3.05 m ahead; worlds differ in radius / speed
    sc = make_scenario([agent(0.0, 0.0, speed=10.0, goal=(3.05, 0.0))])
    sim = cpsim.Simulator([sc], num_worlds=4, max_agents=1, seed=0)
    conds = np.stack([cond(goal_radius=2.5, goal_speed=12.0),   # 2.05 m < 2.5 after step 1
                      cond(goal_radius=2.0, goal_speed=12.0),   # 1.05 m < 2 only after step 2
                      cond(goal_radius=3.0, goal_speed=5.0),    # too fast: never
                      cond(goal_radius=12.0, goal_speed=30.0)])[:, None]  # inside at t0: first test at step 1
    sim.reset(conditions=conds)
    goal_steps = np.full(4, -1)
    for t in range(1, 4):
        sim.step(np.full((4, 1), KEEP_JERK))
        newly = (sim.metrics["goal_step"][:, 0].numpy() == t)
        goal_steps[newly] = t
    assert goal_steps.tolist() == [1, 2, -1, 1]
    assert sim.outcome[:, 0].tolist() == [Outcome.GOAL, Outcome.GOAL, Outcome.RUNNING, Outcome.GOAL]
    assert sim.alive[:, 0].tolist() == [False, False, True, False]


def _pair(config=None, W=1):
    # ego (slot 0) 10 m/s faster than the car 8 m ahead in its lane: they collide within 1 s.
    # Slots follow distance to the ego: slot 1 = the car beside it (3.7 m), slot 2 = the one ahead.
    sc = make_scenario([agent(0.0, 0.0, speed=15.0, goal=(120.0, 0.0)),
                        agent(8.0, 0.0, speed=5.0, goal=(120.0, 0.0)),
                        agent(0.0, LANE_WIDTH, speed=5.0, goal=(120.0, LANE_WIDTH))])
    sim = cpsim.Simulator([sc], num_worlds=W, max_agents=3, seed=0, config=config)
    sim.reset(conditions=NORMAL)
    assert sim.agent_index[0].tolist() == [0, 2, 1]
    return sim


EGO, SIDE, AHEAD = 0, 1, 2


def _run_until_collision(sim, max_steps=20):
    for _ in range(max_steps):
        sim.step(np.full((sim.num_worlds, sim.max_agents), KEEP_JERK))
        if (sim.metrics["first_collision_step"][0] >= 0).any():
            return
    raise AssertionError("no collision")


def test_removed_agents_are_invisible_to_observations_and_collisions():
    sim = _pair()
    layout = sim.obs_layout
    partners = layout.split(sim.obs)["partners"]
    assert partners[0, SIDE, :, -1].sum().item() == 2  # the side car sees both others at reset
    _run_until_collision(sim)
    m = sim.metrics
    assert m["collision_partner"][0, [EGO, AHEAD]].tolist() == [AHEAD, EGO]
    assert sim.outcome[0, [EGO, AHEAD]].tolist() == [Outcome.COLLISION, Outcome.COLLISION]
    pair = [EGO, AHEAD]
    assert sim.done[0, pair].all() and sim.terminated[0, pair].all() and not sim.truncated[0].any()
    assert not sim.alive[0, pair].any() and sim.alive[0, SIDE] and not sim.done[0, SIDE]
    assert np.all(sim.obs[0, pair].numpy() == 0)
    partners = layout.split(sim.obs)["partners"]
    assert partners[0, SIDE, :, -1].sum().item() == 0  # nobody left to see
    # the side car is moved onto the removed cars' position: no collision with ghosts
    sim.set_controllers(np.array([Controller.POLICY, Controller.STATIC, Controller.POLICY]))
    sim.xy[0, SIDE] = sim.xy[0, AHEAD].clone()
    sim.step(np.full((1, 3), KEEP_JERK))
    assert m["first_collision_step"][0, SIDE].item() == -1
    assert not sim.done[0].any()  # done only on the step the episode ended


def test_stop_rule_keeps_agent_as_static_obstacle():
    sim = _pair({"on_collision": "stop"})
    _run_until_collision(sim)
    pair = [EGO, AHEAD]
    t = sim.step_count[0].item()
    assert sim.alive[0, pair].all() and sim.done[0, pair].all()
    assert sim.controllers[0, pair].tolist() == [Controller.STATIC, Controller.STATIC]
    assert not sim.policy_mask[0, pair].any()
    xy = sim.xy[0, pair].clone()
    sim.step(np.full((1, 3), KEEP_JERK))
    np.testing.assert_allclose(sim.xy[0, pair].numpy(), xy.numpy())
    assert (sim.speed[0, pair] == 0).all() and not sim.done[0].any()
    assert sim.metrics["first_collision_step"][0, EGO].item() == t  # sticky, not re-recorded
    assert sim.outcome[0, EGO].item() == Outcome.COLLISION


def test_ignore_rule_records_and_continues():
    sim = _pair({"on_collision": "ignore"})
    _run_until_collision(sim)
    pair = [EGO, AHEAD]
    assert sim.alive[0, pair].all() and not sim.done[0, pair].any()
    assert sim.outcome[0, EGO].item() == Outcome.COLLISION
    assert sim.reward_terms["raw_collision"][0, EGO].item() == 1.0
    assert sim.policy_mask[0, pair].all()


def test_timeout_world_done_and_frozen_after_the_end():
    sc = make_scenario([agent(0.0, 0.0, speed=5.0, goal=(120.0, 0.0)),
                        agent(0.0, LANE_WIDTH, speed=5.0, goal=(120.0, LANE_WIDTH))])
    sim = cpsim.Simulator([sc], num_worlds=2, max_agents=2, seed=0, config={"episode_steps": 5})
    sim.reset(conditions=NORMAL)
    for t in range(1, 6):
        assert not sim.world_done.any()
        sim.step(np.full((2, 2), KEEP_JERK))
        assert sim.step_count.tolist() == [t, t]
    assert sim.world_done.all()
    assert sim.done.all() and sim.truncated.all() and not sim.terminated.any()
    assert (sim.outcome == Outcome.TIMEOUT).all()
    assert sim.metrics["steps_alive"].tolist() == [[5, 5], [5, 5]]
    before = sim.state_dict()
    sim.step(np.full((2, 2), KEEP_JERK))  # the episode is over: nothing moves
    after = sim.state_dict()
    np.testing.assert_array_equal(before["pos"], after["pos"])
    assert sim.step_count.tolist() == [5, 5] and not sim.done.any() and (sim.reward == 0).all()


def test_world_done_when_no_policy_agent_is_left():
    sc = make_scenario([agent(0.0, 0.0, speed=15.0, goal=(14.0, 0.0)),
                        agent(50.0, LANE_WIDTH, speed=5.0, goal=(120.0, LANE_WIDTH))])
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=2, seed=0)
    sim.reset(conditions=np.stack([cond(goal_radius=3.0, goal_speed=20.0), NORMAL]))
    sim.set_controllers(np.array([Controller.POLICY, Controller.IDM]))
    assert not sim.world_done[0]
    while sim.alive[0, 0]:  # the ego reaches its goal (and is removed) after 8 steps
        sim.step(np.full((1, 2), KEEP_JERK))
    assert sim.world_done[0] and sim.alive[0, 1]
    sim.set_controllers(np.array([Controller.POLICY, Controller.POLICY]))
    assert not sim.world_done[0]  # recomputed after a controller change


def test_comfort_counts_longitudinal_or_lateral_jerk():
    """A steering step at 3 m/s: |a_lat| ~ 1 m/s^2 (< 3) but its lateral jerk ~ 10 m/s^3 (> 5)
    is a comfort violation; longitudinal and lateral jerk together still count once."""
    sc = make_scenario([agent(0.0, 0.0, speed=3.0, goal=(200.0, 0.0))])
    sim = cpsim.Simulator([sc], num_worlds=2, max_agents=1, seed=0, config={"dynamics": "classic"})
    sim.reset(conditions=cond(comfort=0.1))
    steer, steer_accel = 3 * 13 + 9, 6 * 13 + 9  # steer 0.5 rad with accel 0 / +4 m/s^2
    v = 3.0
    beta = math.tanh(0.5 * math.tan(0.5))
    a_lat = v * v * math.cos(beta) * math.tan(0.5) / 4.5
    sim.step(np.array([[steer], [steer_accel]]))
    st = sim.state_dict()
    assert abs(st["jerk"][0, 0]) < 1e-4 and st["lat_accel"][0, 0] == pytest.approx(a_lat, rel=1e-4)
    assert abs(st["lat_accel"][0, 0]) < 3.0 and st["lat_jerk"][0, 0] == pytest.approx(a_lat / 0.1, rel=1e-4)
    # world 1: longitudinal jerk 40 and lateral jerk > 5 in the same step, a_long 4 > 3
    assert abs(st["jerk"][1, 0]) > 5.0 and abs(st["lat_jerk"][1, 0]) > 5.0
    assert sim.metrics["comfort_violations"][:, 0].tolist() == [1, 2]
    assert sim.reward_terms["raw_comfort"][:, 0].tolist() == [1.0, 2.0]
    assert sim.reward_terms["w_comfort"][0, 0].item() == pytest.approx(-0.1)
    sim.step(np.array([[steer], [steer]]))   # same steering, constant speed: a_lat barely changes
    sim.step(np.array([[3 * 13 + 6], [3 * 13 + 6]]))  # straighten: lateral jerk ~ -10 again
    assert sim.metrics["comfort_violations"][0, 0].item() == 2
    np.testing.assert_array_equal(comfort_violations_np([0.0, 4.0, 0.0], [0.0, 0.0, 3.5], [0.0, 6.0, 0.0],
                                                        [6.0, 6.0, 0.0]), [1, 2, 1])
