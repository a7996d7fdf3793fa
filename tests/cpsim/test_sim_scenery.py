"""Tracked agents and scenery: which agents get every event and metric (``Simulator(track_all=...)``).

Scenery (REPLAY / STATIC agents without a task, slot > 0) skips the lane query, the metrics
accumulators and the reward, and is tested for collisions with tracked agents only. What the
evaluation reads must not change: the tracked agents' every field, and co-player harm
(other vehicles that collided or went off-road) for everything the ego and co-players do.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import warp as wp

import cpsim
from cpsim.config import Controller, Outcome
from cpsim.kernels.common import KERNEL_MODULE
from cpsim.kernels.metrics import offroad_test
from cpsim.model import ModelArrays
from cpsim.state import METRIC_FIELDS, state_field_names
from tests.cpsim.scenes import LANE_WIDTH, agent, make_scenario

KEEP_JERK = 2 * 3 + 1  # zero jerks: constant speed, straight
WOMD_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "womd"


def scene():
    """Ego (task) drives into a parked car (scenery); a replayed car without a task (goal at
    its start) drives into a second parked car in the other lane; a third parked car stands
    across the road edge (off-road)."""
    return make_scenario([
        agent(0.0, 0.0, speed=10.0, goal=(80.0, 0.0)),                       # ego, task agent
        agent(15.0, 0.0, goal=(15.0, 0.0)),                                  # parked, ego's lane
        agent(15.0, LANE_WIDTH, goal=(15.0, LANE_WIDTH)),                    # parked, other lane
        agent(0.0, LANE_WIDTH, speed=10.0, goal=(0.0, LANE_WIDTH)),          # replayed, no task
        agent(40.0, -1.85, goal=(40.0, -1.85)),                              # parked across the road edge
    ], sid="scenery")


def run(track_all: bool, steps: int = 30, **cfg):
    sc = scene()
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=sc.num_agents, seed=0, track_all=track_all,
                          config=cfg or None)
    for _ in range(steps):
        sim.step(np.full((1, sim.max_agents), KEEP_JERK))
    return sim, sc


def slot_of(sim, agent_index):
    return int(np.flatnonzero(sim.agent_index[0].numpy() == agent_index)[0])


def harm(sim) -> np.ndarray:
    """Co-player harm per world, as ``cpalgo.evaluate.runner`` computes it."""
    met = {k: v.numpy() for k, v in sim.metrics.items()}
    harmed = (met["first_collision_step"] >= 0) | (met["first_offroad_step"] >= 0)
    harmed[:, 0] = False
    vehicle = sim.agent_index.numpy() >= 0  # every agent of these scenes is a vehicle
    return (harmed & vehicle).sum(1)


def test_roles():
    sim, sc = run(False, steps=0)
    assert sim.task_agent[0].tolist() == [bool(c) for c in sc.controllable[sim.agent_index[0].numpy()]]
    assert sim.task_agent[0].sum().item() == 1 and sim.task_agent[0, 0]
    assert (sim.controllers[0, 1:] == int(Controller.REPLAY)).all()


def test_ego_hitting_scenery_is_recorded_on_both_sides():
    sim, _ = run(False)
    parked = slot_of(sim, 1)
    m = {k: v[0].numpy() for k, v in sim.metrics.items()}
    t = m["first_collision_step"][0]
    assert t > 0 and m["collision_partner"][0] == parked
    assert m["first_collision_step"][parked] == t and m["collision_partner"][parked] == 0
    assert sim.outcome[0, 0].item() == Outcome.COLLISION  # (the parked car stands on its goal: GOAL first)
    # off-road scenery is recorded too (from the first step)
    off = slot_of(sim, 4)
    assert m["first_offroad_step"][off] == 1 and sim.outcome[0, off].item() == Outcome.OFFROAD


def test_scenery_skips_lane_metrics_and_reward_tracked_agents_unchanged():
    fast, _ = run(False, steps=12)
    full, _ = run(True, steps=12)
    a, b = fast.state_dict(), full.state_dict()
    tracked = np.zeros(fast.max_agents, bool)
    tracked[0] = True
    for name in state_field_names() + ("obs",):
        if a[name].ndim == 1:  # per world
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)
        else:
            np.testing.assert_array_equal(a[name][0, tracked], b[name][0, tracked], err_msg=name)
    np.testing.assert_array_equal(a["obs"], b["obs"])
    scenery = ~tracked
    assert (b["steps_alive"][0, scenery] > 0).all()  # computed with track_all
    for name in ("steps_alive", "comfort_violations", "aligned_steps", "lateral_offset_sum", "reward",
                 "reward_raw", "reward_w", "lane_err", "lane_offset", "has_lane"):
        assert not a[name][0, scenery].any(), name


def test_collisions_between_two_scenery_agents_need_track_all():
    fast, _ = run(False)
    full, _ = run(True)
    mover, parked2 = slot_of(fast, 3), slot_of(fast, 2)
    col_fast = fast.metrics["first_collision_step"][0].numpy()
    col_full = full.metrics["first_collision_step"][0].numpy()
    assert col_full[mover] > 0 and col_full[parked2] == col_full[mover]
    assert col_fast[mover] == -1 and col_fast[parked2] == -1
    # everything else agrees, and harm differs by exactly the scenery pair
    others = np.ones(fast.max_agents, bool)
    others[[mover, parked2]] = False
    for name in ("first_collision_step", "collision_partner", "first_offroad_step", "goal_step", "at_fault"):
        np.testing.assert_array_equal(fast.metrics[name][0].numpy()[others], full.metrics[name][0].numpy()[others],
                                      err_msg=name)
    assert harm(fast).tolist() == [2] and harm(full).tolist() == [4]


@pytest.mark.parametrize("rule", ["remove", "stop"])
def test_policy_and_idm_coplayers_are_tracked(rule):
    """A non-task agent switched to IDM (world 0) or POLICY (world 1) is tracked: its every
    field and its collisions with scenery are those of the track_all run."""
    sc = scene()
    res = []
    for track_all in (False, True):
        sim = cpsim.Simulator([sc], num_worlds=2, max_agents=sc.num_agents, seed=0, track_all=track_all,
                              config={"on_collision": rule, "on_goal": "ignore"})
        mover = slot_of(sim, 3)
        ctrl = sim.controllers.numpy().copy()
        ctrl[0, mover] = int(Controller.IDM)
        ctrl[1, mover] = int(Controller.POLICY)
        sim.set_controllers(ctrl)
        for _ in range(30):
            sim.step(np.full((2, sim.max_agents), KEEP_JERK))
        res.append(sim.state_dict())
    tracked = [0, mover]
    for name in METRIC_FIELDS + ("outcome", "alive", "controller", "reward", "reward_raw", "obs"):
        np.testing.assert_array_equal(res[0][name][:, tracked], res[1][name][:, tracked], err_msg=name)
    for name in ("first_collision_step", "first_offroad_step", "outcome", "alive"):
        np.testing.assert_array_equal(res[0][name], res[1][name], err_msg=name)
    # the policy-driven mover (world 1) drove into the parked car of its lane, which records it too
    parked2 = slot_of(sim, 2)
    assert (res[0]["first_collision_step"][1, [mover, parked2]] > 0).all()


@pytest.mark.skipif(not any(WOMD_DIR.glob("*.json")), reason=f"real WOMD files not found in {WOMD_DIR}")
@pytest.mark.parametrize("regime", [Controller.REPLAY, Controller.IDM, Controller.STATIC, Controller.POLICY])
def test_womd_coplayer_harm_and_tracked_state_match_track_all(regime):
    """Random policy egos on the real WOMD scenes, co-players (task agents) in each regime:
    harm per world, every tracked agent's state and every observation equal the
    track_all run (the logs hold no collision between two replayed agents)."""
    from cpsim.scenario import load

    scs = [load(p) for p in sorted(WOMD_DIR.glob("*.json"))]
    W, A = 6, 64
    out = []
    for track_all in (False, True):
        sim = cpsim.Simulator(scs, num_worlds=W, max_agents=A, seed=3, track_all=track_all)
        sim.reset(scenario_index=np.arange(W) % len(scs))
        ctrl = sim.controllers.numpy().copy()
        task = sim.task_agent.numpy()
        ctrl[:, 1:][task[:, 1:]] = int(regime)
        ctrl[:, 0] = int(Controller.POLICY)
        sim.set_controllers(ctrl)
        rng = np.random.default_rng(0)
        for _ in range(91):
            sim.step(rng.integers(0, sim.num_actions, size=(W, A)))
        out.append((sim.state_dict(), harm_womd(sim, scs), sim.task_agent.numpy().copy()))
    (a, harm_a, task), (b, harm_b, _) = out
    assert harm_a.tolist() == harm_b.tolist()
    tracked = task.copy()
    tracked[:, 0] = True
    tracked |= np.isin(a["controller"], [int(Controller.POLICY), int(Controller.IDM)])
    for name in state_field_names():
        if a[name].ndim >= 2:
            np.testing.assert_array_equal(a[name][tracked], b[name][tracked], err_msg=name)
    np.testing.assert_array_equal(a["obs"], b["obs"])
    # scenery: off-road and goal as with track_all (collisions differ only between two scenery
    # agents, e.g. pedestrians walking side by side, which harm does not count)
    for name in ("first_offroad_step", "goal_step"):
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def harm_womd(sim, scs) -> np.ndarray:
    met = {k: v.numpy() for k, v in sim.metrics.items()}
    harmed = (met["first_collision_step"] >= 0) | (met["first_offroad_step"] >= 0)
    harmed[:, 0] = False
    idx = sim.agent_index.numpy()
    scen = sim.world_scenario.numpy()
    vehicle = np.zeros_like(harmed)
    for w in range(idx.shape[0]):
        ok = idx[w] >= 0
        vehicle[w, ok] = scs[scen[w]].agent_types[idx[w, ok]] == cpsim.AgentType.VEHICLE
    return (harmed & vehicle).sum(1)


@wp.kernel(module=KERNEL_MODULE + "_test_replay_offroad", enable_backward=False)
def live_offroad_kernel(model: ModelArrays, box_scale: float, out: wp.array2d(dtype=wp.bool)):
    """The events kernel's off-road test (trigonometry inline) on every logged move."""
    row, t = wp.tid()
    hit = bool(False)
    if t > 0 and model.agent_type[row] == 0:
        size = model.size[row]
        hit = offroad_test(model, model.agent_scenario[row], model.log_xy[row, t], model.log_heading[row, t],
                           model.log_xy[row, t - 1], model.log_heading[row, t - 1],
                           0.5 * (size[0] * box_scale), 0.5 * (size[1] * box_scale))
    out[row, t] = hit


def test_replay_offroad_table_matches_the_live_test():
    """``Model.arrays.log_offroad`` equals the events kernel's off-road test on every logged
    move, and a replayed agent's recorded off-road step is the table's first hit."""
    scs = [scene()]
    if any(WOMD_DIR.glob("*.json")):
        from cpsim.scenario import load

        scs += [load(p) for p in sorted(WOMD_DIR.glob("*.json"))]
    for box_scale in (1.0, 0.7):
        sim = cpsim.Simulator(scs, num_worlds=len(scs), max_agents=64, seed=0, track_all=True,
                              config={"box_scale": box_scale, "default_controller": "replay"})
        m = sim.model
        out = wp.zeros(m.arrays.log_offroad.shape, dtype=wp.bool)
        wp.launch(live_offroad_kernel, dim=out.shape, inputs=[m.arrays, box_scale, out])
        table = m.arrays.log_offroad.numpy()
        np.testing.assert_array_equal(table, out.numpy())
        assert table.any()
        sim.reset(scenario_index=np.arange(len(scs)))
        for _ in range(40):
            sim.step(np.zeros((sim.num_worlds, sim.max_agents), np.int64))
        rows = sim.state.agent_row.numpy()
        first = sim.metrics["first_offroad_step"].numpy()
        valid = m.arrays.log_valid.numpy()
        for w in range(sim.num_worlds):
            for a in np.flatnonzero(rows[w] >= 0):
                r = rows[w, a]
                gone = np.flatnonzero(~valid[r, 1:41])  # a replayed agent leaves when its log ends
                last = gone[0] if gone.size else 40
                hits = np.flatnonzero(table[r, 1:last + 1]) + 1
                assert first[w, a] == (hits[0] if hits.size else -1), (w, a)
