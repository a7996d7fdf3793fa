"""Dynamics: jerk and classic models against hand-computed steps; replay, static and IDM."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

import cpsim
from cpsim.config import CLASSIC_ACCEL, CLASSIC_STEER, Controller
from cpsim.kernels.dynamics import classic_step_np, jerk_step_np
from tests.cpsim.scenes import agent, make_scenario

NORMAL = cpsim.profile("normal")


def _solo(speed=10.0, length=4.5, heading=0.0, dynamics="jerk", y=0.0):
    sc = make_scenario([agent(0.0, y, heading=heading, speed=speed, length=length, goal=(200.0, y))])
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=2, config={"dynamics": dynamics}, seed=0)
    sim.reset(conditions=NORMAL)
    return sim


def _act(sim, action):
    acts = np.zeros((1, 2), np.int64)
    acts[0, 0] = action
    sim.step(acts)


def test_jerk_longitudinal_hand_computed():
    # v = 10, a = 0, steer = 0, length 5 (wheelbase 3); long jerk +4 (idx 3), lat 0 (idx 1)
    sim = _solo(speed=10.0, length=5.0)
    _act(sim, 3 * 3 + 1)
    a_long = 0.4                                   # 0 + 4 * 0.1
    v = 10.0 + 0.5 * (a_long + 0.0) * 0.1          # 10.02
    # a zero lateral command is zero curvature: straight ahead (no 1e-5 floor)
    assert sim.accel[0, 0].item() == pytest.approx(a_long, abs=1e-6)
    assert sim.speed[0, 0].item() == pytest.approx(v, abs=1e-5)
    assert sim.steer[0, 0].item() == 0.0
    assert sim.xy[0, 0, 0].item() == pytest.approx(1.001, abs=1e-5)
    assert sim.xy[0, 0, 1].item() == 0.0
    assert sim.heading[0, 0].item() == 0.0


def test_jerk_can_steer_right_after_a_left_turn():
    # PufferDrive's curvature floor made +epsilon steering absorbing: after any left turn
    # every right jerk was reset to 0 by the sign-change rule and the agent drove straight.
    sim = _solo(speed=10.0, length=4.5)
    for action in [2 * 3 + 2] * 5 + [2 * 3 + 0] * 15:
        _act(sim, action)
    state = dict(x=0.0, y=0.0, heading=0.0, vx=10.0, vy=0.0, a_long=0.0, a_lat=0.0, steer=0.0)
    for j_lat in [4.0] * 5 + [-4.0] * 15:
        new = jerk_step_np(*state.values(), sim.size[0, 0, 0].item(), 0.0, j_lat)
        state = {k: new[k] for k in state}
    assert state["a_lat"] < -2.0 and state["steer"] < -0.02 and state["heading"] < -0.05
    # float64 reaches exactly zero steering one step later than float32; same shape
    assert sim.steer[0, 0].item() == pytest.approx(state["steer"], abs=0.015)
    assert sim.heading[0, 0].item() == pytest.approx(state["heading"], abs=0.05)
    assert sim.heading[0, 0].item() < -0.05 and bool(sim.alive[0, 0])


def test_jerk_refused_speed_change_zeroes_the_acceleration():
    # braking hard to a stop: the limiter refuses the sign change, so a_long is 0 after it
    # (PufferDrive kept a_long = -5 and the next steps drove backwards)
    sim = _solo(speed=1.0, length=4.5)
    for _ in range(10):
        _act(sim, 0 * 3 + 1)                       # long jerk -15 until the car stands
        if sim.speed[0, 0].item() <= 0.0:
            break
    assert sim.speed[0, 0].item() == 0.0
    assert sim.accel[0, 0].item() == 0.0
    _act(sim, 2 * 3 + 1)                           # zero jerk: stays stopped, not reversing
    assert sim.speed[0, 0].item() == 0.0
    _act(sim, 3 * 3 + 1)                           # +4 jerk: moves forward at once
    assert sim.speed[0, 0].item() > 0.0


def test_jerk_lateral_hand_computed():
    # lateral jerk +4 (idx 2), long 0 (idx 2): a_lat = 0.4, curvature 0.4 / 100 = 0.004
    sim = _solo(speed=10.0, length=5.0)
    _act(sim, 2 * 3 + 2)
    steer = math.atan(0.004 * 3.0)  # within the 0.06 rad rate limit
    assert sim.steer[0, 0].item() == pytest.approx(steer, abs=1e-6)
    assert sim.speed[0, 0].item() == pytest.approx(10.0, abs=1e-6)
    assert sim.xy[0, 0, 0].item() == pytest.approx(math.sin(0.004) / 0.004, abs=1e-5)
    assert sim.xy[0, 0, 1].item() == pytest.approx((1 - math.cos(0.004)) / 0.004, abs=1e-5)
    assert sim.heading[0, 0].item() == pytest.approx(0.004, abs=1e-6)


def test_jerk_steering_rate_limit_and_lateral_accel():
    # at 2 m/s the target steering atan(0.1 * 3) = 0.29 rad exceeds the 0.06 rad/step limit
    sim = _solo(speed=2.0, length=5.0)
    _act(sim, 2 * 3 + 2)
    assert sim.steer[0, 0].item() == pytest.approx(0.06, abs=1e-6)
    a_lat = sim.state.lat_accel.numpy()[0, 0]
    assert a_lat == pytest.approx(4.0 * math.tan(0.06) / 3.0, rel=1e-4)


def test_jerk_matches_reference_over_random_actions():
    sim = _solo(speed=6.0, length=4.5)
    rng = np.random.default_rng(1)
    ref = dict(x=0.0, y=0.0, heading=0.0, vx=6.0, vy=0.0, a_long=0.0, a_lat=0.0, steer=0.0)
    for _ in range(25):
        act = int(rng.integers(0, 12))
        _act(sim, act)
        if not sim.alive[0, 0]:
            break
        out = jerk_step_np(ref["x"], ref["y"], ref["heading"], ref["vx"], ref["vy"], ref["a_long"],
                           ref["a_lat"], ref["steer"], 4.5, [-15.0, -4.0, 0.0, 4.0][act // 3],
                           [-4.0, 0.0, 4.0][act % 3])
        ref = {k: out[k] for k in ref}
        np.testing.assert_allclose(sim.xy[0, 0].numpy(), [ref["x"], ref["y"]], atol=2e-3)
        assert sim.heading[0, 0].item() == pytest.approx(ref["heading"], abs=1e-4)
        assert sim.speed[0, 0].item() == pytest.approx(out["speed"], abs=1e-4)
        assert sim.accel[0, 0].item() == pytest.approx(ref["a_long"], abs=1e-5)
    # hard braking stops at 0 instead of reversing through it
    for _ in range(12):
        _act(sim, 0 * 3 + 1)
    assert sim.speed[0, 0].item() >= -2.0


def test_classic_hand_computed_pufferdrive():
    sim = _solo(speed=10.0, length=4.5, dynamics="classic")
    assert sim.num_actions == 91
    _act(sim, 4 * 13 + 8)  # accel 1.333, steer 1/3 rad
    a, delta = float(CLASSIC_ACCEL[4]), float(CLASSIC_STEER[8])
    # PufferDrive's steering table is rounded to three decimals, not exactly 1/3
    assert a == pytest.approx(1.333) and delta == pytest.approx(0.333, abs=1e-7)
    v_new = 10.0 + a * 0.1
    beta = math.tanh(0.5 * math.tan(delta))
    yaw = v_new * math.cos(beta) * math.tan(delta) / 4.5  # the updated, signed speed
    assert sim.xy[0, 0, 0].item() == pytest.approx(v_new * math.cos(beta) * 0.1, abs=1e-5)
    assert sim.xy[0, 0, 1].item() == pytest.approx(v_new * math.sin(beta) * 0.1, abs=1e-5)
    assert sim.heading[0, 0].item() == pytest.approx(yaw * 0.1, abs=1e-6)
    np.testing.assert_allclose(sim.velocity[0, 0].numpy(), [v_new * math.cos(beta), v_new * math.sin(beta)],
                               atol=1e-5)
    # a second step uses the new heading and |velocity|
    _act(sim, 3 * 13 + 6)  # accel 0, steer 0
    ref = classic_step_np(v_new * math.cos(beta) * 0.1, v_new * math.sin(beta) * 0.1, yaw * 0.1,
                          v_new * math.cos(beta), v_new * math.sin(beta), 4.5, 0.0, 0.0)
    np.testing.assert_allclose(sim.xy[0, 0].numpy(), [ref["x"], ref["y"]], atol=1e-5)


PUFFERDRIVE_CSV = Path(__file__).resolve().parents[2].parent / "shared/data/pufferdrive/classic_kinematics.csv"


def _pufferdrive_sequences() -> dict[str, list[dict[str, str]]]:
    with PUFFERDRIVE_CSV.open(newline="") as f:
        rows = list(csv.DictReader(f))
    seqs: dict[str, list[dict[str, str]]] = {}
    for r in rows:
        seqs.setdefault(r["sequence"], []).append(r)
    return seqs


@pytest.mark.skipif(not PUFFERDRIVE_CSV.is_file(), reason="PufferDrive reference trajectories absent")
@pytest.mark.parametrize("box_scale", [1.0, 0.7])
def test_classic_reproduces_pufferdrive_trajectories(box_scale):
    """PufferDrive's own classic step (float32, 4 x 90 decisions) within float32 rounding.

    With ``box_scale`` 0.7 the logged length is the CSV's / 0.7: the yaw rate divides by
    box_scale x length, as PufferDrive does for the agents it controls on WOMD."""
    seqs = _pufferdrive_sequences()
    assert len(seqs) == 4
    scenarios, ref = [], []
    for name, rows in seqs.items():
        r0 = rows[0]
        length = float(r0["length"]) / box_scale
        assert all(float(r["length"]) == float(r0["length"]) for r in rows)
        x, y, h, v = (float(r0[k]) for k in ("x", "y", "heading", "speed"))
        scenarios.append(make_scenario([agent(x, y, heading=h, speed=v, length=length, goal=(x + 5000.0, y))],
                                       sid=name))
        ref.append(rows)
    cfg = {"dynamics": "classic", "box_scale": box_scale, "on_goal": "ignore", "on_collision": "ignore",
           "on_offroad": "ignore"}
    sim = cpsim.Simulator(scenarios, num_worlds=4, max_agents=1, config=cfg, seed=0)
    sim.reset(scenario_index=np.arange(4), conditions=NORMAL)
    np.testing.assert_allclose(sim.velocity[:, 0].numpy(),
                               [[float(r[0]["vx"]), float(r[0]["vy"])] for r in ref], atol=1e-5)
    n = len(ref[0]) - 1
    assert n == 90 and all(len(r) == n + 1 for r in ref)
    err_xy = np.zeros(4)
    err_h = np.zeros(4)
    for t in range(1, n + 1):
        sim.step(np.array([[int(r[t]["action"])] for r in ref]))
        assert bool(sim.alive[:, 0].all())
        want_xy = np.array([[float(r[t]["x"]), float(r[t]["y"])] for r in ref])
        want_h = np.array([float(r[t]["heading"]) for r in ref])  # never wrapped there
        want_v = np.array([[float(r[t]["vx"]), float(r[t]["vy"])] for r in ref])
        err_xy = np.maximum(err_xy, np.abs(sim.xy[:, 0].numpy() - want_xy).max(-1))
        dh = sim.heading[:, 0].numpy().astype(np.float64) - want_h
        err_h = np.maximum(err_h, np.abs((dh + np.pi) % (2 * np.pi) - np.pi))
        np.testing.assert_allclose(sim.velocity[:, 0].numpy(), want_v, atol=1e-3)
    # float32 rounding only (positions reach 1000 m, where one ulp is 6e-5 m)
    assert err_xy.max() < 1e-3, dict(zip(seqs, err_xy))
    assert err_h.max() < 1e-4, dict(zip(seqs, err_h))


def test_classic_yaw_rate_follows_box_scale():
    """One steering step: the yaw rate divides by box_scale x the logged length."""
    headings = []
    for box_scale in (1.0, 0.7):
        sc = make_scenario([agent(0.0, 0.0, speed=10.0, length=5.0, goal=(200.0, 0.0))])
        sim = cpsim.Simulator([sc], num_worlds=1, max_agents=2,
                              config={"dynamics": "classic", "box_scale": box_scale}, seed=0)
        sim.reset(conditions=NORMAL)
        _act(sim, 3 * 13 + 9)  # accel 0, steer 0.5
        headings.append(sim.heading[0, 0].item())
    beta = math.tanh(0.5 * math.tan(0.5))
    yaw = 10.0 * math.cos(beta) * math.tan(0.5) / 5.0
    assert headings[0] == pytest.approx(yaw * 0.1, rel=1e-5)
    assert headings[1] == pytest.approx(yaw * 0.1 / 0.7, rel=1e-5)


def test_replay_follows_log_and_vanishes_when_log_ends():
    sc = make_scenario([
        agent(0.0, 0.0, speed=5.0, goal=(100.0, 0.0)),
        agent(20.0, 3.7, speed=7.0, accel=0.5, valid_steps=6, goal=(21.0, 3.7)),  # not controllable
    ])
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=2, seed=0)
    sim.reset(conditions=NORMAL)
    assert sim.controllers[0].tolist() == [Controller.POLICY, Controller.REPLAY]
    for t in range(1, 6):
        sim.step(np.full((1, 2), 7))
        np.testing.assert_allclose(sim.xy[0, 1].numpy(), sc.log_xy[1, t], atol=1e-6)
        assert sim.speed[0, 1].item() == pytest.approx(np.linalg.norm(sc.log_velocity[1, t]), abs=1e-5)
        # its goal is 1 m from its start: no task, so it never arrives (and replay is never removed)
        assert sim.alive[0, 1] and not sim.done[0, 1]
    assert sim.outcome[0, 1].item() == cpsim.Outcome.RUNNING and sim.metrics["goal_step"][0, 1].item() == -1
    sim.step(np.full((1, 2), 7))  # log step 6 is invalid: the agent leaves
    assert not sim.alive[0, 1] and sim.done[0, 1] and sim.truncated[0, 1]
    assert not sim.terminated[0, 1]


def test_static_holds_pose_with_zero_speed():
    sc = make_scenario([agent(0.0, 0.0, speed=5.0, goal=(100.0, 0.0)), agent(30.0, 3.7, speed=6.0, goal=(99.0, 3.7))])
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=2, seed=0)
    sim.reset(conditions=NORMAL)
    sim.set_controllers(np.array([Controller.POLICY, Controller.STATIC]))
    for _ in range(3):
        sim.step(np.full((1, 2), 7))
    np.testing.assert_allclose(sim.xy[0, 1].numpy(), [30.0, 3.7], atol=1e-6)
    assert sim.speed[0, 1].item() == 0.0


def test_idm_follows_path_and_stops_behind_a_stopped_leader():
    # follower at 10 m/s along +x; a parked car 40 m ahead in the same lane
    sc = make_scenario([
        agent(0.0, 0.0, speed=10.0, goal=(150.0, 0.0)),
        agent(40.0, 0.0, speed=0.0),
    ])
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=2, seed=0, config={"on_goal": "ignore"})
    sim.reset(conditions=NORMAL)
    sim.set_controllers(np.array([Controller.IDM, Controller.STATIC]))
    for _ in range(90):
        sim.step(np.zeros((1, 2), np.int64))
    x = sim.xy[0, 0, 0].item()
    gap = 40.0 - x - 4.5
    assert sim.alive[0, 0] and sim.outcome[0, 0].item() in (cpsim.Outcome.RUNNING, cpsim.Outcome.TIMEOUT)
    assert sim.metrics["first_collision_step"][0, 0].item() == -1
    assert 0.5 < gap < 6.0, gap  # stopped close behind, never hit it
    assert abs(sim.xy[0, 0, 1].item()) < 1e-3 and abs(sim.speed[0, 0].item()) < 0.2


def test_idm_parameters_are_behaviorbench_defaults():
    cfg = cpsim.SimConfig()
    assert (cfg.idm_v0, cfg.idm_min_gap, cfg.idm_headway, cfg.idm_accel, cfg.idm_brake) == (15.0, 1.0, 1.5, 1.0, 3.0)
    # free road: a = a_max (1 - (v / v0)^4) with v0 = 15 m/s whatever the logged speed
    sc = make_scenario([agent(0.0, 0.0, speed=10.0, goal=(200.0, 0.0))])  # logged speed 10 m/s
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=1, seed=0, config={"on_goal": "ignore"})
    sim.reset(conditions=NORMAL)
    sim.set_controllers(np.array([Controller.IDM]))
    sim.step(np.zeros((1, 1), np.int64))
    assert sim.speed[0, 0].item() == pytest.approx(10.0 + 0.1 * (1.0 - (10.0 / 15.0) ** 4), abs=1e-5)
    # behind a stopped leader: s* = s0 + v T + v dv / (2 sqrt(a b)), a -= a_max (s* / gap)^2
    sc = make_scenario([agent(0.0, 0.0, speed=10.0, goal=(200.0, 0.0)), agent(35.0, 0.0, speed=0.0)])
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=2, seed=0, config={"on_goal": "ignore"})
    sim.reset(conditions=NORMAL)
    sim.set_controllers(np.array([Controller.IDM, Controller.STATIC]))
    sim.step(np.zeros((1, 2), np.int64))
    gap = 35.0 - 4.5  # within the 40 m lookahead
    s_star = 1.0 + 10.0 * 1.5 + 10.0 * 10.0 / (2.0 * math.sqrt(1.0 * 3.0))
    acc = 1.0 * (1.0 - (10.0 / 15.0) ** 4 - (s_star / gap) ** 2)
    assert sim.speed[0, 0].item() == pytest.approx(10.0 + 0.1 * acc, abs=1e-5)


def test_idm_free_road_reaches_desired_speed_without_exceeding_it():
    sc = make_scenario([agent(0.0, 0.0, speed=4.0, accel=1.0, goal=(200.0, 0.0))])  # log max ~13 m/s
    # idm_v0 = 0: each agent's largest logged speed is its desired speed
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=1, seed=0,
                          config={"on_goal": "ignore", "idm_v0": 0.0, "idm_accel": 2.0})
    sim.reset(conditions=NORMAL)
    sim.set_controllers(np.array([Controller.IDM]))
    v0 = float(np.linalg.norm(sc.log_velocity[0], axis=-1).max())
    speeds = []
    for _ in range(60):
        sim.step(np.zeros((1, 1), np.int64))
        speeds.append(sim.speed[0, 0].item())
    assert max(speeds) <= v0 + 1e-4
    assert speeds[-1] > 0.8 * v0
    assert abs(sim.xy[0, 0, 1].item()) < 1e-3
