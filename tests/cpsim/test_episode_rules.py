"""BehaviorBench's episode rules in training (SelfPlayVecEnv over the simulator):
controlled agents, removal without respawn, 91 steps with truncation, world reset when
no controlled agent is left, and the learner's bootstrap of truncated steps."""

from __future__ import annotations

import numpy as np
import pytest

from cpsim import SelfPlayVecEnv
from cpsim.scenario.datatypes import AgentType
from tests.cpsim.scenes import LANE_WIDTH, agent, make_scenario

KEEP = 3 * 13 + 6  # classic: accel 0, steer 0


def _scene():
    return make_scenario([
        agent(0.0, 0.0, speed=10.0, goal=(12.0, 0.0)),                       # reaches its goal in about 1 s
        agent(40.0, LANE_WIDTH, speed=0.0, goal=(200.0, LANE_WIDTH)),         # stands: times out
        agent(-30.0, LANE_WIDTH, speed=0.0, kind=AgentType.PEDESTRIAN, goal=(0.0, LANE_WIDTH)),
        agent(100.0, 0.0, speed=0.0, goal=(101.0, 0.0)),                      # goal 1 m away: no task
    ], sid="rules")


def _env(scenarios, **kw):
    return SelfPlayVecEnv(scenarios, num_worlds=1, max_agents=4, seed=0, dynamics="classic", condition="normal", **kw)


def test_controlled_agents_removal_truncation_and_world_reset():
    env = _env([_scene()])
    obs = env.reset()
    active = env.active_mask()
    # controlled: the two vehicles valid at t0 with a goal >= 2 m away; not the pedestrian, not the 1 m goal
    assert active.sum() == 2
    rows = {int(i) for i in np.flatnonzero(active)}
    goal_slot = next(i for i in rows if env.sim.agent_index[0, i] == 0)
    wait_slot = next(i for i in rows if env.sim.agent_index[0, i] == 1)
    t, goal_at = 0, None
    actions = np.full(env.num_envs, KEEP)
    while True:
        env.step_async(actions)
        obs, rew, done, infos = env.step_wait()
        t += 1
        if goal_at is None and done[goal_slot]:
            goal_at = t
            assert infos[goal_slot]["outcome"] == "goal" and rew[goal_slot] == pytest.approx(1.0, abs=0.01)
            assert not infos[goal_slot]["TimeLimit.truncated"]
        elif goal_at is not None and t < 91:
            # removed: no respawn, an inactive zero slot with zero reward until the world resets
            assert not env.active_mask()[goal_slot] and not done[goal_slot] and rew[goal_slot] == 0.0
            assert np.all(obs[goal_slot] == 0.0)
            assert int(env.sim.alive[0, goal_slot]) == 0
        if done[wait_slot]:
            break
    assert goal_at is not None and goal_at < 20
    # the waiting car runs the full 91 steps and is truncated (bootstrapped), not terminated
    assert t == 91 and infos[wait_slot]["outcome"] == "timeout" and infos[wait_slot]["TimeLimit.truncated"]
    # the world reset on that step: both controlled agents are back, new episode's observation
    assert env.active_mask()[goal_slot] and env.active_mask()[wait_slot]
    assert not np.all(obs[goal_slot] == 0.0)


def test_world_resets_on_the_step_its_last_controlled_agent_leaves():
    lone = make_scenario([agent(0.0, 0.0, speed=10.0, goal=(12.0, 0.0))], sid="lone")
    env = _env([lone])
    env.reset()
    slot = int(np.flatnonzero(env.active_mask())[0])
    steps = 0
    while True:
        env.step_async(np.full(env.num_envs, KEEP))
        obs, rew, done, infos = env.step_wait()
        steps += 1
        if done[slot] or steps >= 91:
            break
    assert infos[slot]["outcome"] == "goal" and steps < 20
    # no dead steps: the returned observation already belongs to the next episode
    assert env.active_mask()[slot] and int(env.sim.step_count[0]) == 0
    assert infos[slot]["terminal_observation"] is not None


def test_collided_agents_leave_and_are_not_collidable():
    crash = make_scenario([agent(0.0, 0.0, speed=15.0, goal=(200.0, 0.0)),
                           agent(8.0, 0.0, speed=0.0, goal=(200.0, 0.0)),
                           agent(-20.0, 0.0, speed=15.0, goal=(200.0, 0.0))], sid="crash")
    env = _env([crash])
    env.reset()
    index = env.sim.agent_index[0].tolist()
    front, hit, follower = index.index(0), index.index(1), index.index(2)
    outcomes = {}
    for t in range(1, 40):
        env.step_async(np.full(env.num_envs, KEEP))
        _, _, done, infos = env.step_wait()
        for i in (front, hit, follower):
            if done[i] and i not in outcomes:
                outcomes[i] = (infos[i]["outcome"], t)
    assert outcomes[front][0] == "collision" and outcomes[hit][0] == "collision"
    # the follower drives through the spot where both were removed without a collision
    assert follower not in outcomes or outcomes[follower][0] != "collision"
    assert int(env.sim.alive[0, front]) == 0 and int(env.sim.alive[0, hit]) == 0
