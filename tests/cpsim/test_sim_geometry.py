"""Geometry through the simulator: SAT collisions, off-road (crossing, grazing, tunnelling),
lane queries and the nuPlan fault rule against the NumPy references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import cpsim
from cpsim.config import Controller
from cpsim.kernels.geometry import (box_corners_np, boxes_overlap_np, classify_collision,
                                    classify_fault)
from tests.cpsim.scenes import EDGE_HIGH, LANE_WIDTH, agent, make_scenario

NORMAL = cpsim.profile("normal")


def place(sim, w, a, x, y, heading=0.0, speed=0.0, length=None, width=None):
    """Overwrite an agent's pose through the zero-copy state views."""
    sim.xy[w, a] = torch.tensor([x, y])
    sim.heading[w, a] = heading
    sim.velocity[w, a] = torch.tensor([speed * math.cos(heading), speed * math.sin(heading)])
    sim.speed[w, a] = speed
    if length is not None:
        sim.size[w, a, 0] = length
    if width is not None:
        sim.size[w, a, 1] = width


@pytest.fixture(scope="module")
def pair_sim():
    sc = make_scenario([agent(100.0, 0.0, goal=(180.0, 0.0)), agent(120.0, 3.7, goal=(190.0, 3.7))])
    return cpsim.Simulator([sc], num_worlds=64, max_agents=2, seed=0)


def _static_pairs(sim):
    sim.reset(conditions=NORMAL)
    sim.set_controllers(np.array([Controller.STATIC, Controller.STATIC]))


def _collided(sim):
    return (sim.metrics["first_collision_step"] >= 0).numpy()


def test_sat_touching_separated_and_rotated(pair_sim):
    sim = pair_sim
    _static_pairs(sim)
    cases = [
        # (x, y, heading) of agent 1 relative to agent 0 at (100, 0, 0); boxes 4 x 2 m
        ((104.0, 0.0, 0.0), True),                     # touching end to end
        ((104.01, 0.0, 0.0), False),                   # 1 cm apart
        ((100.0, 2.0, 0.0), True),                     # touching side by side
        ((100.0, 2.01, 0.0), False),
        ((103.99, 1.99, 0.0), True),                   # corners overlapping by 1 cm
        ((102.0 + math.sqrt(2) - 0.01, 0.0, math.pi / 4), True),   # 2x2 square rotated 45 deg:
        ((102.0 + math.sqrt(2) + 0.01, 0.0, math.pi / 4), False),  # its corner at the face
        ((101.0, 2.2, math.pi / 2), True),             # crossing T: the other's end in our side
        ((101.0, 3.01, math.pi / 2), False),
    ]
    for w, ((x, y, h), _) in enumerate(cases):
        place(sim, w, 0, 100.0, 0.0, 0.0, length=4.0, width=2.0)
        size = (2.0, 2.0) if h == math.pi / 4 else (4.0, 2.0)
        place(sim, w, 1, x, y, h, length=size[0], width=size[1])
    sim.step(np.zeros((64, 2), np.int64))
    got = _collided(sim)
    for w, ((x, y, h), expect) in enumerate(cases):
        assert got[w, 0] == expect and got[w, 1] == expect, (w, x, y, h)
        if expect:
            assert sim.metrics["collision_partner"][w, 0].item() == 1
            assert sim.metrics["collision_partner"][w, 1].item() == 0


def test_sat_matches_reference_on_random_boxes(pair_sim):
    sim = pair_sim
    _static_pairs(sim)
    rng = np.random.default_rng(0)
    W = sim.num_worlds
    poses = []
    for w in range(W):
        while True:
            xy = np.array([100.0, 0.0]) + rng.uniform(-5, 5, 2)
            h0, h1 = rng.uniform(-np.pi, np.pi, 2)
            s0, s1 = rng.uniform([2, 1], [6, 2.5]), rng.uniform([2, 1], [6, 2.5])
            # keep away from exact touching so float32 vs float64 cannot disagree
            near = [boxes_overlap_np(np.array([100.0, 0.0]), h0, s0 * f, xy, h1, s1 * f) for f in (0.999, 1.001)]
            if near[0] == near[1]:
                break
        poses.append((h0, s0, xy, h1, s1, near[0]))
        place(sim, w, 0, 100.0, 0.0, h0, length=s0[0], width=s0[1])
        place(sim, w, 1, xy[0], xy[1], h1, length=s1[0], width=s1[1])
    sim.step(np.zeros((W, 2), np.int64))
    got = _collided(sim)[:, 0]
    expect = np.array([p[5] for p in poses])
    assert 5 < expect.sum() < W - 5  # both cases well represented
    np.testing.assert_array_equal(got, expect)


def test_box_scale_shrinks_collision_boxes():
    sc = make_scenario([agent(100.0, 0.0, goal=(180.0, 0.0)), agent(104.5, 0.0, goal=(190.0, 0.0))])
    for scale, expect in ((1.0, True), (0.7, False)):
        sim = cpsim.Simulator([sc], num_worlds=1, max_agents=2, seed=0, config={"box_scale": scale})
        sim.reset(conditions=NORMAL)
        place(sim, 0, 1, 104.4, 0.0)  # 4.5 m boxes overlap by 10 cm; at 0.7 they are 1.25 m apart
        sim.set_controllers(np.array([Controller.STATIC, Controller.STATIC]))
        sim.step(np.zeros((1, 2), np.int64))
        assert bool(_collided(sim)[0, 0]) == expect


def test_pedestrians_collide_only_when_configured():
    sc = make_scenario([agent(100.0, 0.0, goal=(180.0, 0.0)),
                        agent(102.0, 0.0, length=0.8, width=0.8, kind=cpsim.AgentType.PEDESTRIAN)])
    for collide, expect in ((True, True), (False, False)):
        sim = cpsim.Simulator([sc], num_worlds=1, max_agents=2, seed=0, config={"collide_types": collide})
        sim.reset(conditions=NORMAL)
        sim.set_controllers(np.array([Controller.STATIC, Controller.STATIC]))
        sim.step(np.zeros((1, 2), np.int64))
        assert bool(_collided(sim)[0, 0]) == expect


# ----------------------------------------------------------------------------- off-road
def _solo_sim(config=None, W=1):
    sc = make_scenario([agent(100.0, 0.0, speed=0.0, goal=(200.0, 0.0))])
    sim = cpsim.Simulator([sc], num_worlds=W, max_agents=1, seed=0,
                          config={"dynamics": "classic", **(config or {})})
    sim.reset(conditions=NORMAL)
    return sim


KEEP = 3 * 13 + 6  # classic: accel 0, steer 0


def test_offroad_on_a_crossing_path():
    sim = _solo_sim()
    # drive at 2 m/s, 30 deg to the left, towards the upper edge (y = 5.55) from y = 2
    place(sim, 0, 0, 100.0, 2.0, math.radians(30), speed=2.0, length=4.0, width=2.0)
    steps = 0
    while sim.alive[0, 0] and steps < 40:
        before = box_corners_np(sim.xy[0, 0].numpy(), sim.heading[0, 0].item(), np.array([4.0, 2.0]))
        sim.step(np.full((1, 1), KEEP))
        steps += 1
    assert sim.outcome[0, 0].item() == cpsim.Outcome.OFFROAD
    assert sim.metrics["first_offroad_step"][0, 0].item() == steps
    # the step it was flagged is the first whose box reaches the edge
    assert before[:, 1].max() < EDGE_HIGH
    after = box_corners_np(sim.xy[0, 0].numpy(), sim.heading[0, 0].item(), np.array([4.0, 2.0]))
    assert after[:, 1].max() >= EDGE_HIGH
    assert not sim.alive[0, 0] and sim.done[0, 0] and sim.terminated[0, 0]


@pytest.mark.parametrize("clearance,expect", [(0.05, False), (-0.05, True)])
def test_offroad_grazing_path(clearance, expect):
    sim = _solo_sim({"on_offroad": "ignore"})
    # drive along the upper edge, box side `clearance` m from it (negative: overlapping)
    y = EDGE_HIGH - 1.0 - clearance
    place(sim, 0, 0, 100.0, y, 0.0, speed=5.0, length=4.0, width=2.0)
    for _ in range(20):
        sim.step(np.full((1, 1), KEEP))
    assert (sim.metrics["first_offroad_step"][0, 0].item() >= 0) == expect
    assert sim.alive[0, 0]


def test_offroad_swept_test_catches_tunnelling():
    sim = _solo_sim()
    # 80 m/s straight across the upper edge: one step moves 8 m, from fully inside the
    # road to fully beyond the edge; only the swept corner paths see the crossing
    place(sim, 0, 0, 100.0, 1.0, math.pi / 2, speed=80.0, length=4.0, width=2.0)
    sim.step(np.full((1, 1), KEEP))
    y = sim.xy[0, 0, 1].item()
    assert y - 2.0 > EDGE_HIGH  # the box is past the edge
    assert sim.outcome[0, 0].item() == cpsim.Outcome.OFFROAD


def test_pedestrians_are_not_offroad():
    sc = make_scenario([agent(100.0, 0.0, goal=(200.0, 0.0)),
                        agent(110.0, 5.5, speed=1.0, heading=math.pi / 2, length=0.8, width=0.8,
                              kind=cpsim.AgentType.PEDESTRIAN)])
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=2, seed=0)
    sim.reset(conditions=NORMAL)
    for _ in range(5):
        sim.step(np.full((1, 2), 7))
    assert sim.metrics["first_offroad_step"][0, 1].item() == -1


# ----------------------------------------------------------------------------- lanes
def test_lane_queries_offset_heading_error_and_no_lane():
    sim = _solo_sim({"on_offroad": "ignore"}, W=4)
    sim.set_controllers(np.array([Controller.STATIC]))
    place(sim, 0, 0, 100.0, 0.5, 0.1)          # 0.5 m left of lane 0, 0.1 rad error
    place(sim, 1, 0, 100.0, 2.0, -0.2)         # nearer lane 1 (y = 3.7): 1.7 m to its right
    place(sim, 2, 0, 100.0, 30.0, 0.0)         # far from any lane
    place(sim, 3, 0, 100.0, 0.0, math.pi)      # wrong way
    sim.step(np.zeros((4, 1), np.int64))
    st = sim.state
    off, err, has = st.lane_offset.numpy()[:, 0], st.lane_err.numpy()[:, 0], st.has_lane.numpy()[:, 0]
    assert has.tolist() == [True, True, False, True]
    assert off[0] == pytest.approx(0.5, abs=1e-4) and err[0] == pytest.approx(0.1, abs=1e-5)
    assert off[1] == pytest.approx(2.0 - LANE_WIDTH, abs=1e-4) and err[1] == pytest.approx(-0.2, abs=1e-5)
    assert abs(err[3]) == pytest.approx(math.pi, abs=1e-5)
    m = sim.metrics
    # aligned: heading error below 15 deg (0.1 and 0.2 rad are); no lane -> offset 10 m
    assert m["aligned_steps"][:, 0].tolist() == [1, 1, 0, 0]
    np.testing.assert_allclose(m["lateral_offset_sum"][:, 0].numpy(), [0.5, LANE_WIDTH - 2.0, 10.0, 0.0],
                               atol=1e-4)


def test_at_fault_matches_reference():
    sc = make_scenario([agent(100.0, 0.0, goal=(180.0, 0.0)), agent(120.0, 3.7, goal=(190.0, 3.7))])
    W = 48
    sim = cpsim.Simulator([sc], num_worlds=W, max_agents=2, seed=0, config={"on_collision": "ignore"})
    sim.reset(conditions=NORMAL)
    sim.set_controllers(np.array([Controller.STATIC, Controller.STATIC]))
    rng = np.random.default_rng(3)
    cases = []
    for w in range(W):
        while True:
            h0 = rng.uniform(-0.4, 0.4)
            y0 = rng.uniform(-0.5, 4.2)
            rel = rng.uniform(-4.5, 4.5, 2)
            h1 = rng.uniform(-np.pi, np.pi)
            v0, v1 = rng.choice([0.0, 3.0, 8.0]), rng.choice([0.0, 4.0])
            p0, p1 = np.array([100.0, y0]), np.array([100.0, y0]) + rel
            if boxes_overlap_np(p0, h0, np.array([4.5, 2.0]) * 0.999, p1, h1, np.array([4.5, 2.0]) * 0.999) \
                    and boxes_overlap_np(p0, h0, np.array([4.5, 2.0]) * 1.001, p1, h1, np.array([4.5, 2.0]) * 1.001):
                break
        cases.append((p0, h0, v0, p1, h1, v1))
        place(sim, w, 0, *p0, h0)
        place(sim, w, 1, *p1, h1)
    sim.step(np.zeros((W, 2), np.int64))
    # STATIC agents have speed 0 during the events test, so poke speeds via a second look:
    # the kernel saw speed 0 for both -> "stopped ego" -> never at fault
    assert not sim.metrics["at_fault"].any()
    # now with moving agents: REPLAY would overwrite poses, so use POLICY + classic keep action
    sim2 = cpsim.Simulator([sc], num_worlds=W, max_agents=2, seed=0,
                           config={"on_collision": "ignore", "dynamics": "classic"})
    sim2.reset(conditions=NORMAL)
    for w, (p0, h0, v0, p1, h1, v1) in enumerate(cases):
        # place so that after one straight step at speed v the boxes sit at the sampled poses
        place(sim2, w, 0, *(p0 - 0.1 * v0 * np.array([math.cos(h0), math.sin(h0)])), h0, speed=v0)
        place(sim2, w, 1, *(p1 - 0.1 * v1 * np.array([math.cos(h1), math.sin(h1)])), h1, speed=v1)
    sim2.step(np.full((W, 2), KEEP))
    got = sim2.metrics["at_fault"].numpy()[:, 0]
    collided = (sim2.metrics["first_collision_step"] >= 0).numpy()[:, 0]
    assert collided.all()
    lanes = np.array([0.0, LANE_WIDTH])
    expect = []
    for (p0, h0, v0, p1, h1, v1) in cases:
        kind = classify_collision(p0, h0, v0, np.array([4.5, 2.0]), p1, h1, v1, np.array([4.5, 2.0]))
        corners = box_corners_np(p0, h0, np.array([4.5, 2.0]))
        d = np.abs(corners[:, 1:2] - lanes[None])  # lanes are the lines y = 0 and y = 3.7
        ids = {int(np.argmin(r)) for r in d if r.min() <= 4.0}
        expect.append(classify_fault(kind, len(ids) > 1))
    expect = np.array(expect)
    assert expect.any() and not expect.all()
    np.testing.assert_array_equal(got, expect)
