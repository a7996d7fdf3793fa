"""BehaviorBench's reward: each term against its formula on hand-made inputs (the Warp
function itself), and the simulator's summed terms over a 1,000-step rollout against the
NumPy reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

import cpsim
from cpsim.conditions import FIELD_INDEX
from cpsim.kernels.reward import comfort_violations_np, reward_terms_np, write_reward
from cpsim.state import REWARD_TERMS

DT = 0.1


@wp.kernel
def _reward_probe(conds: wp.array3d(dtype=wp.float32), flags: wp.array2d(dtype=wp.int32),
                  values: wp.array2d(dtype=wp.float32), raw: wp.array3d(dtype=wp.float32),
                  weighted: wp.array3d(dtype=wp.float32), reward: wp.array(dtype=wp.float32)):
    i = wp.tid()
    reward[i] = write_reward(conds, raw, weighted, i, 0, flags[i, 0] != 0, flags[i, 1] != 0, flags[i, 2] != 0,
                             flags[i, 3], flags[i, 4] != 0, values[i, 0], values[i, 1], values[i, 2],
                             values[i, 3], DT)


def kernel_terms(cases: list[dict]) -> tuple[list[dict], list[dict], np.ndarray]:
    """Run :func:`write_reward` in a Warp kernel on hand-made inputs (one case per thread)."""
    n = len(cases)
    conds = np.stack([c["cond"] for c in cases])[:, None, :].astype(np.float32)
    flags = np.array([[c.get("goal", 0), c.get("collided", 0), c.get("offroad", 0), c.get("violations", 0),
                       c.get("has_lane", 1)] for c in cases], np.int32)
    values = np.array([[c.get("err", 0.0), c.get("offset", 0.0), c.get("speed", 0.0), c.get("accel", 0.0)]
                       for c in cases], np.float32)
    raw = wp.zeros((n, 1, len(REWARD_TERMS)), dtype=wp.float32, device="cpu")
    wtd = wp.zeros((n, 1, len(REWARD_TERMS)), dtype=wp.float32, device="cpu")
    rew = wp.zeros(n, dtype=wp.float32, device="cpu")
    wp.launch(_reward_probe, dim=n, inputs=[wp.array(conds, device="cpu"), wp.array(flags, device="cpu"),
                                            wp.array(values, device="cpu"), raw, wtd, rew], device="cpu")
    raw_np, w_np = raw.numpy()[:, 0], wtd.numpy()[:, 0]
    as_dicts = [[dict(zip(REWARD_TERMS, row.tolist())) for row in arr] for arr in (raw_np, w_np)]
    return as_dicts[0], as_dicts[1], rew.numpy()


def cond(**fields) -> np.ndarray:
    c = cpsim.profile("normal").copy()
    for k, v in fields.items():
        c[FIELD_INDEX[k]] = v
    return c


C = cond(collision=2.0, offroad=1.5, comfort=0.05, lane_align=0.02, vel_align=0.5, lane_center=0.005,
         center_bias=0.3, reverse=0.004)


def test_goal_collision_offroad_comfort_are_not_scaled_by_dt():
    raw, wtd, rew = kernel_terms([
        dict(cond=C, goal=1, speed=3.0),                     # goal alone
        dict(cond=C, goal=1, collided=1, speed=8.0),         # goal and collision in one step: no goal
        dict(cond=C, offroad=1, speed=5.0),
        dict(cond=C, violations=2, speed=5.0),
    ])
    assert raw[0]["goal"] == 1.0 and wtd[0]["goal"] == 1.0
    assert raw[1]["goal"] == 0.0 and raw[1]["collision"] == 1.0
    assert wtd[1]["collision"] == pytest.approx(-(2.0 + 0.1 * 8.0))
    assert wtd[2]["offroad"] == pytest.approx(-1.5) and raw[2]["offroad"] == 1.0
    assert raw[3]["comfort"] == 2.0 and wtd[3]["comfort"] == pytest.approx(-0.05 * 2)


def test_lane_alignment_penalises_only_driving_against_the_lane():
    errs = [0.0, 0.3, 2.5, -2.5]
    raw, wtd, _ = kernel_terms([dict(cond=C, err=e, speed=10.0) for e in errs]
                               + [dict(cond=C, has_lane=0, speed=10.0, err=0.7)])
    for k, e in enumerate(errs):
        want = min(math.cos(e), 0.0) + 0.0025 * (1 - abs(e) / (math.pi / 2))
        assert raw[k]["lane_align"] == pytest.approx(want, abs=1e-6)
        assert wtd[k]["lane_align"] == pytest.approx(0.02 * DT * want, abs=1e-9)
        assert raw[k]["vel_align"] == pytest.approx(min(10.0 * math.cos(e), 0.0), abs=1e-5)
        assert wtd[k]["vel_align"] == pytest.approx(0.02 * 0.5 * DT * min(10.0 * math.cos(e), 0.0), abs=1e-8)
    # a small heading error costs nothing any more (the old cos th - 1 charged it): a bonus remains
    assert raw[1]["lane_align"] > 0 and raw[1]["vel_align"] == 0.0
    # no lane within 4 m: th = pi, so -1 - 0.0025 and the whole speed counts against
    assert raw[4]["lane_align"] == pytest.approx(-1.0 - 0.0025)
    assert raw[4]["vel_align"] == pytest.approx(-10.0)


def test_lane_centring_only_near_a_lane_with_bias_and_bonus():
    # offsets are the lane query's (left positive); the term measures right positive
    raw, wtd, _ = kernel_terms([dict(cond=C, offset=-1.0, err=0.1), dict(cond=C, offset=0.5, err=0.1),
                                dict(cond=C, offset=-0.3, err=0.1), dict(cond=C, offset=-1.0, err=1.2),
                                dict(cond=C, offset=-1.0, has_lane=0)])
    d = abs(1.0 - 0.3)
    assert raw[0]["lane_center"] == pytest.approx(d - 0.05 * math.exp(0.5 - d), abs=1e-6)
    assert wtd[0]["lane_center"] == pytest.approx(-0.005 * DT * (d - 0.05 * math.exp(0.5 - d)), abs=1e-9)
    d = abs(-0.5 - 0.3)
    assert raw[1]["lane_center"] == pytest.approx(d - 0.05 * math.exp(0.5 - d), abs=1e-6)
    # on the biased centre: only the bonus, a positive reward
    assert raw[2]["lane_center"] == pytest.approx(-0.05 * math.exp(0.5), abs=1e-6) and wtd[2]["lane_center"] > 0
    # heading more than 60 deg off the lane: no distance charge, the bonus only
    assert raw[3]["lane_center"] == pytest.approx(-0.05 * math.exp(0.5 - 0.7), abs=1e-6)
    assert raw[4]["lane_center"] == 0.0 and wtd[4]["lane_center"] == 0.0


def test_reversing_velocity_and_time_terms():
    raw, wtd, _ = kernel_terms([dict(cond=C, speed=-1.0), dict(cond=C, speed=5.0, err=0.4),
                                dict(cond=C, speed=2.0, err=0.0), dict(cond=C, speed=5.0, has_lane=0),
                                dict(cond=C, speed=0.0, accel=0.0), dict(cond=C, speed=0.0, accel=1.0)])
    assert raw[0]["reverse"] == 1.0 and wtd[0]["reverse"] == pytest.approx(-0.004 * DT)
    assert raw[1]["reverse"] == 0.0
    assert raw[1]["velocity"] == pytest.approx(math.cos(0.4)) and wtd[1]["velocity"] == pytest.approx(
        0.0025 * DT * math.cos(0.4))
    assert raw[2]["velocity"] == 0.0 and raw[3]["velocity"] == 0.0   # too slow; no lane
    assert [raw[k]["time"] for k in range(6)] == [1.0, 1.0, 1.0, 1.0, 0.0, 1.0]
    assert wtd[5]["time"] == pytest.approx(-2.5e-5 * DT)


def test_kernel_equals_reference_and_sum_on_random_inputs():
    rng = np.random.default_rng(0)
    conds = cpsim.sample_conditions(rng, (64,))
    cases = [dict(cond=conds[i], goal=int(rng.random() < 0.2), collided=int(rng.random() < 0.2),
                  offroad=int(rng.random() < 0.2), violations=int(rng.integers(0, 4)),
                  has_lane=int(rng.random() < 0.7), err=float(rng.uniform(-np.pi, np.pi)),
                  offset=float(rng.uniform(-4, 4)), speed=float(rng.uniform(-3, 20)),
                  accel=float(rng.uniform(-4, 4))) for i in range(64)]
    raw, wtd, rew = kernel_terms(cases)
    for k, c in enumerate(cases):
        r_raw, r_w, r_sum = reward_terms_np(c["cond"], goal_now=c["goal"], collided=c["collided"],
                                            offroad=c["offroad"], violations=c["violations"],
                                            has_lane=c["has_lane"], err=c["err"], offset=c["offset"],
                                            speed=c["speed"], accel=c["accel"], dt=DT)
        for t in REWARD_TERMS:
            assert raw[k][t] == pytest.approx(float(r_raw[t]), rel=1e-5, abs=1e-5), t
            assert wtd[k][t] == pytest.approx(float(r_w[t]), rel=1e-5, abs=1e-7), t
        assert rew[k] == pytest.approx(sum(wtd[k].values()), rel=1e-5, abs=1e-6)
        assert rew[k] == pytest.approx(float(r_sum), rel=1e-5, abs=1e-6)


def test_rollout_of_1000_steps_matches_the_numpy_reference():
    """Random actions over 11 episodes of 91 steps (1,001 steps) on procedural scenes, every
    agent on p_train conditions: the kernel's weighted terms summed over the rollout equal the
    reference's, computed from the simulator's own post-step state."""
    pool = cpsim.scenario.train_pool(4, 0)
    sim = cpsim.Simulator(pool, num_worlds=4, max_agents=8, seed=0, config={"dynamics": "classic"})
    rng = np.random.default_rng(1)
    got = dict.fromkeys(REWARD_TERMS, 0.0)
    want = dict.fromkeys(REWARD_TERMS, 0.0)
    got_reward = want_reward = 0.0
    steps = 0
    events = dict(goal=0, collided=0, offroad=0, lane=0)
    while steps < 1000:
        sim.reset()
        for t in range(91):
            before = sim.state_dict()
            present = before["alive"] & (before["controller"] == int(cpsim.Controller.POLICY))
            sim.step(rng.integers(0, 91, size=(4, 8)))
            st = sim.state_dict()
            kw = dict(goal_now=st["goal_step"] == t + 1, collided=st["first_collision_step"] == t + 1,
                      offroad=st["first_offroad_step"] == t + 1,
                      violations=comfort_violations_np(st["accel"], st["lat_accel"], st["jerk"], st["lat_jerk"]),
                      has_lane=st["has_lane"], err=st["lane_err"], offset=st["lane_offset"], speed=st["speed"],
                      accel=st["accel"], dt=DT)
            _, r_w, r_sum = reward_terms_np(st["conditions"], **kw)
            for i, term in enumerate(REWARD_TERMS):
                got[term] += float(st["reward_w"][..., i][present].sum())
                want[term] += float(r_w[term][present].sum())
                assert np.all(st["reward_w"][..., i][~present] == 0.0)
            got_reward += float(st["reward"][present].sum())
            want_reward += float(r_sum[present].sum())
            for k in ("goal_now", "collided", "offroad"):
                events[{"goal_now": "goal"}.get(k, k)] += int((kw[k] & present).sum())
            events["lane"] += int((st["has_lane"] & present).sum())
            steps += 1
    assert steps == 1001
    for term in REWARD_TERMS:
        assert got[term] == pytest.approx(want[term], rel=1e-5, abs=1e-5), term
    assert got_reward == pytest.approx(want_reward, rel=1e-5, abs=1e-5)
    # the rollout exercised the terms it compares
    assert events["collided"] > 0 and events["offroad"] > 0 and events["lane"] > 0
