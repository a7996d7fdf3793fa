"""Geometry through the simulator: SAT collisions, off-road (crossing, grazing, tunnelling),
lane queries and the nuPlan fault rule against the NumPy references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import cpsim
from cpsim.config import Controller
from cpsim.kernels import geometry as G
from cpsim.kernels.geometry import box_corners_np, boxes_overlap_np, lane_distance_np
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
    sim = _solo_sim({"on_offroad": "ignore"}, W=5)
    sim.set_controllers(np.array([Controller.STATIC]))
    place(sim, 0, 0, 100.0, 0.5, 0.1)          # 0.5 m left of lane 0, 0.1 rad error
    place(sim, 1, 0, 100.0, 2.0, -0.2)         # nearer lane 1 (y = 3.7): 1.7 m to its right
    place(sim, 2, 0, 100.0, 30.0, 0.0)         # far from any lane (outside the grid)
    place(sim, 3, 0, 100.0, 0.0, math.pi)      # wrong way
    place(sim, 4, 0, 100.0, -7.0, 0.0)         # 7 m right of lane 0: beyond the 4 m lane radius
    sim.step(np.zeros((5, 1), np.int64))
    st = sim.state
    off, err, has = st.lane_offset.numpy()[:, 0], st.lane_err.numpy()[:, 0], st.has_lane.numpy()[:, 0]
    assert has.tolist() == [True, True, False, True, False]
    assert off[0] == pytest.approx(0.5, abs=1e-4) and err[0] == pytest.approx(0.1, abs=1e-5)
    assert off[1] == pytest.approx(2.0 - LANE_WIDTH, abs=1e-4) and err[1] == pytest.approx(-0.2, abs=1e-5)
    assert abs(err[3]) == pytest.approx(math.pi, abs=1e-5)
    m = sim.metrics
    # aligned: heading error below 15 deg (0.1 and 0.2 rad are); with no lane within 4 m the
    # lane_center metric still takes the true distance (no 10 m placeholder)
    assert m["aligned_steps"][:, 0].tolist() == [1, 1, 0, 0, 0]
    np.testing.assert_allclose(m["lateral_offset_sum"][:, 0].numpy(),
                               [0.5, LANE_WIDTH - 2.0, 30.0 - LANE_WIDTH, 0.0, 7.0], atol=1e-4)


def _lane_segments_of(host, g):
    """(S, 4) lane segments and (S,) polyline ids of scenario g of a model (from its cells' lists)."""
    first = int(host["grid_first"][g])
    last = first + int(np.prod(host["grid_dims"][g]))
    ids = np.unique(host["lane_items"][host["lane_start"][first]:host["lane_start"][last]])
    return np.concatenate([host["seg_a"][ids], host["seg_b"][ids]], 1), host["seg_poly"][ids]


def test_true_lane_distance_matches_reference_on_curved_maps():
    """The ring search over the grid equals the brute-force distance to every lane segment."""
    from cpsim.scenario.procedural import generate

    scs = [generate(fam, seed=3) for fam in ("intersection", "roundabout", "merge")]
    W = 96
    sim = cpsim.Simulator(scs, num_worlds=W, max_agents=1, seed=0,
                          config={"on_offroad": "ignore", "on_collision": "ignore"})
    sim.reset(scenario_index=np.arange(W) % len(scs), conditions=NORMAL)
    sim.set_controllers(np.full((W, 1), int(Controller.STATIC)))
    host = sim.model.host
    rng = np.random.default_rng(0)
    pts = np.zeros((W, 2))
    for w in range(W):
        seg, _ = _lane_segments_of(host, w % len(scs))
        lo, hi = seg.reshape(-1, 2).min(0) - 30.0, seg.reshape(-1, 2).max(0) + 30.0
        pts[w] = rng.uniform(lo, hi)
        place(sim, w, 0, *pts[w], 0.0)
        sim.state.goal.numpy()[w, 0] = pts[w] + 1000.0
    sim.step(np.zeros((W, 1), np.int64))
    got = sim.metrics["lateral_offset_sum"][:, 0].numpy()
    for w in range(W):
        seg, _ = _lane_segments_of(host, w % len(scs))
        assert got[w] == pytest.approx(float(lane_distance_np(pts[w], seg)), abs=2e-3), w
    assert (got > 4.0).sum() >= 10  # many points are beyond the 4 m lane radius


# ----------------------------------------------------------------------------- at fault
CAR = np.array([4.5, 2.0])
PED = cpsim.AgentType.PEDESTRIAN
# (name, ego (x, y, heading, speed), other (x, y, heading, speed), other kind, ego's three
#  positions before the pre-contact one (oldest first; None: it stood there), kind, at fault)
FAULT_CASES = [
    ("ego stopped, hit from behind", (100.0, 0.0, 0.0, 0.0), (95.2, 0.0, 0.0, 5.0), None, None,
     G.STOPPED_EGO, False),
    ("other stopped", (95.2, 0.0, 0.0, 5.0), (100.0, 0.0, 0.0, 0.0), None, None, G.STOPPED_TRACK, True),
    ("rear-ended in lane", (100.0, 0.0, 0.0, 2.0), (95.0, 0.0, 0.0, 8.0), None, None, G.ACTIVE_REAR, False),
    ("rear-ended while straddling", (100.0, 1.0, 0.0, 2.0), (95.0, 1.0, 0.0, 8.0), None,
     [(99.4, 0.5), (99.6, 0.7), (99.8, 0.85)], G.ACTIVE_REAR, True),
    ("front, closing 5 m/s", (95.2, 0.0, 0.0, 8.0), (100.0, 0.0, 0.0, 3.0), None, None, G.ACTIVE_FRONT, True),
    ("ahead but closing 0.4 m/s: lateral", (95.7, 0.0, 0.0, 5.0), (100.0, 0.0, 0.0, 4.6), None, None,
     G.ACTIVE_LATERAL, False),
    ("side swipe by the other, ego in lane", (100.0, 0.0, 0.0, 5.0), (100.0, 2.3, -0.3, 5.0), None, None,
     G.ACTIVE_LATERAL, False),
    ("side swipe while changing lanes", (100.0, 1.0, 0.2, 5.0), (100.0, 3.3, 0.0, 5.0), None,
     [(98.5, 0.3), (99.0, 0.53), (99.5, 0.77)], G.ACTIVE_LATERAL, True),
    ("near two lanes but no drift", (100.0, 1.0, 0.0, 5.0), (100.0, 3.3, -0.3, 5.0), None,
     [(98.5, 1.0), (99.0, 1.0), (99.5, 1.0)], G.ACTIVE_LATERAL, False),
    ("drifting within one lane", (100.0, 0.3, 0.0, 5.0), (100.0, -2.0, 0.3, 5.0), None,
     [(98.5, -0.5), (99.0, -0.2), (99.5, 0.1)], G.ACTIVE_LATERAL, False),
    ("pedestrian", (100.0, 0.0, 0.0, 5.0), (103.0, 1.3, -math.pi / 2, 1.0), PED, None, G.VULNERABLE, True),
    ("pedestrian walks into a stopped ego", (100.0, 0.0, 0.0, 0.0), (100.0, 1.5, -math.pi / 2, 1.5), PED, None,
     G.VULNERABLE, True),
]


def _fault_world(sim, w, ego, other, history):
    for a, (x, y, h, v) in enumerate((ego, other)):
        place(sim, w, a, x, y, h, speed=v)
    # the ring holds the pre-step positions; the step writes slot step_count % 4 = 0
    hist = sim.state.pos_hist.numpy()
    past = history if history is not None else [ego[:2]] * 3
    for k, p in enumerate(past):
        hist[w, 0, k + 1] = p
    hist[w, 1, 1:] = other[:2]


def test_at_fault_hand_made_cases():
    """BehaviorBench's rules, one case each, in the simulator and in the NumPy reference."""
    kinds = {None: cpsim.AgentType.VEHICLE, PED: PED}
    scs = [make_scenario([agent(100.0, 0.0, goal=(180.0, 0.0)),
                          agent(120.0, 3.7, goal=(190.0, 3.7), kind=k)], sid=str(int(k)))
           for k in kinds.values()]
    W = len(FAULT_CASES)
    cfg = {"on_collision": "ignore", "on_offroad": "ignore", "dynamics": "classic"}
    sim = cpsim.Simulator(scs, num_worlds=W, max_agents=2, seed=0, config=cfg)
    sim.reset(scenario_index=[0 if c[3] is None else 1 for c in FAULT_CASES], conditions=NORMAL)
    sim.set_controllers(np.full((W, 2), int(Controller.POLICY)))
    for w, (_, ego, other, _, history, _, _) in enumerate(FAULT_CASES):
        _fault_world(sim, w, ego, other, history)
    sim.step(np.full((W, 2), KEEP))  # both keep their speed and heading for one step
    collided = (sim.metrics["first_collision_step"] >= 0).numpy()[:, 0]
    got = sim.metrics["at_fault"].numpy()[:, 0]
    segs, polys = _lane_segments_of(sim.model.host, 0)  # both scenarios share the road
    for w, (name, ego, other, kind_code, history, kind, fault) in enumerate(FAULT_CASES):
        assert collided[w], name
        assert bool(got[w]) == fault, name
        vel = [np.array([v * math.cos(h), v * math.sin(h)]) for (_, _, h, v) in (ego, other)]
        ref_kind = G.classify_collision(ego[:2], ego[2], vel[0], other[:2], vel[1], kind_code is not None)
        assert ref_kind == kind, (name, G.COLLISION_KIND_NAMES[ref_kind])
        past = history if history is not None else [ego[:2]] * 3
        straddled = G.straddles_divider_np([*past, ego[:2]], ego[2], CAR[1], segs, polys)
        assert G.classify_fault(ref_kind, straddled) == fault, name


def test_at_fault_matches_reference_on_random_contacts():
    sc = make_scenario([agent(100.0, 0.0, goal=(180.0, 0.0)), agent(120.0, 3.7, goal=(190.0, 3.7))])
    W = 64
    cfg = {"on_collision": "ignore", "on_offroad": "ignore", "dynamics": "classic"}
    sim = cpsim.Simulator([sc], num_worlds=W, max_agents=2, seed=0, config=cfg)
    sim.reset(conditions=NORMAL)
    sim.set_controllers(np.full((W, 2), int(Controller.POLICY)))
    rng = np.random.default_rng(3)
    cases = []
    for w in range(W):
        while True:
            h0 = rng.uniform(-0.4, 0.4)
            y0 = rng.uniform(-0.5, 4.2)
            rel = rng.uniform(-4.5, 4.5, 2)
            h1 = rng.uniform(-np.pi, np.pi)
            v0, v1 = rng.choice([0.0, 3.0, 8.0]), rng.choice([0.0, 0.4, 4.0])
            p0, p1 = np.array([100.0, y0]), np.array([100.0, y0]) + rel
            f0, f1 = (np.array([math.cos(h), math.sin(h)]) for h in (h0, h1))
            q0, q1 = p0 + 0.1 * v0 * f0, p1 + 0.1 * v1 * f1  # after one straight step
            if boxes_overlap_np(q0, h0, CAR * 0.999, q1, h1, CAR * 0.999) \
                    and boxes_overlap_np(q0, h0, CAR * 1.001, q1, h1, CAR * 1.001):
                break
        past = [p0 + rng.uniform(-1.0, 0.0) * (k + 1) * np.array([1.0, rng.uniform(-0.4, 0.4)]) for k in range(3)][::-1]
        cases.append((p0, h0, v0, p1, h1, v1, past))
        _fault_world(sim, w, (*p0, h0, v0), (*p1, h1, v1), past)
    sim.step(np.full((W, 2), KEEP))
    got = sim.metrics["at_fault"].numpy()[:, 0]
    assert (sim.metrics["first_collision_step"] >= 0).numpy()[:, 0].all()
    segs, polys = _lane_segments_of(sim.model.host, 0)
    expect, kinds = [], []
    for (p0, h0, v0, p1, h1, v1, past) in cases:
        kind = G.classify_collision(p0, h0, v0 * np.array([math.cos(h0), math.sin(h0)]), p1,
                                    v1 * np.array([math.cos(h1), math.sin(h1)]))
        straddled = G.straddles_divider_np([*past, p0], h0, CAR[1], segs, polys)
        expect.append(G.classify_fault(kind, straddled))
        kinds.append(kind)
    expect = np.array(expect)
    assert expect.any() and not expect.all()
    assert len(set(kinds)) >= 4
    np.testing.assert_array_equal(got, expect)
