"""Evaluation metrics against hand-built trajectories (pure NumPy, no simulator)."""

from __future__ import annotations

import numpy as np
import pytest

from cpalgo.evaluate import metrics as M


# ----------------------------------------------------------------------------- comfort
def test_comfort_violations_counted_per_limit():
    a_long = np.array([0.0, 3.5, -3.5, 3.0, 0.0, 4.0])
    a_lat = np.array([0.0, 0.0, 0.0, -3.0, 3.1, 4.0])
    jerk = np.array([0.0, 0.0, 5.0, 0.0, -6.0, 9.0])
    # limits are strict: exactly 3 / 5 is not a violation
    assert M.comfort_violations(a_long, a_lat, jerk).tolist() == [0, 1, 1, 0, 2, 3]
    # every limit is on the magnitude: negative values count as well
    assert M.comfort_violations([-3.5, 0, 0], [0, -3.5, 0], [0, 0, -5.5]).tolist() == [1, 1, 1]
    # the jerk check counts longitudinal OR lateral jerk (once per step)
    lat_jerk = np.array([6.0, 0.0, -5.0, -5.5, 6.0, 9.0])
    assert M.comfort_violations(a_long, a_lat, jerk, lat_jerk).tolist() == [1, 1, 1, 1, 2, 3]


def test_comfort_metric_matches_definition_and_clamps():
    T = 10
    alive = np.ones((2, T), bool)
    a_long = np.zeros((2, T))
    a_lat = np.zeros((2, T))
    jerk = np.zeros((2, T))
    a_long[0, :4] = 4.0  # 4 violations in 10 steps -> 1 - 4/30
    a_long[1] = 4.0
    a_lat[1] = 4.0
    jerk[1] = 10.0  # every check violated every step -> 0
    m = M.metrics_from_steps(alive, a_long, a_lat, jerk, np.ones((2, T), bool), np.zeros((2, T)))
    np.testing.assert_allclose(m["comfort"], [1 - 4 / 30, 0.0])
    assert m["comfort_violations"].tolist() == [4, 30]


def test_steps_after_removal_are_ignored():
    T = 8
    alive = np.zeros(T, bool)
    alive[:4] = True
    a_long = np.where(alive, 0.0, 10.0)  # violations only where dead
    aligned = np.array([1, 1, 0, 1, 0, 0, 0, 0], bool)
    lat = np.array([0.5, 0.5, 1.0, 1.0, 9, 9, 9, 9])
    m = M.metrics_from_steps(alive, a_long, np.zeros(T), np.zeros(T), aligned, lat)
    assert m["steps_alive"] == 4
    assert m["comfort"] == 1.0
    assert m["lane_align"] == pytest.approx(3 / 4)
    assert m["lane_center"] == pytest.approx(1 - 0.75 / 2)


# ----------------------------------------------------------------------------- lanes
def _straight_lane() -> tuple[np.ndarray, np.ndarray]:
    pts = np.array([[0.0, 0.0], [50.0, 0.0], [100.0, 0.0], [0.0, 20.0], [100.0, 20.0]], np.float32)
    offsets = np.array([0, 3, 5], np.int32)
    types = np.array([0, 2], np.int8)  # one lane, one road edge (ignored)
    return M.lane_segments(pts, offsets, types)


def test_lane_segments_only_lanes_in_order():
    segs, ids = _straight_lane()
    np.testing.assert_allclose(segs, [[0, 0, 50, 0], [50, 0, 100, 0]])
    assert ids.tolist() == [0, 0]
    # lanes of one point or none hold no segment
    pts = np.array([[0.0, 0.0], [5.0, 0.0], [6.0, 0.0], [9.0, 9.0]])
    segs, ids = M.lane_segments(pts, np.array([0, 0, 1, 3, 3, 4]), np.zeros(5, np.int8))
    np.testing.assert_allclose(segs, [[5, 0, 6, 0]])
    assert ids.tolist() == [2]


def test_alignment_threshold_at_15_degrees():
    segs, _ = _straight_lane()
    headings = np.deg2rad([0.0, 14.0, 16.0, 180.0, -14.9])
    xy = np.tile([[30.0, 1.0]], (5, 1))
    q = M.lane_queries(xy, headings, segs)
    assert q["aligned"].tolist() == [True, True, False, False, True]
    np.testing.assert_allclose(q["lateral_offset"], 1.0)
    # the heading error is wrapped: 355 deg and -350 deg are 5 and 10 deg off the lane
    q = M.lane_queries(xy[:3], np.deg2rad([355.0, -350.0, 200.0]), segs)
    assert q["aligned"].tolist() == [True, True, False]
    # the search radius is inclusive: exactly 4 m from the centreline is still near
    q = M.lane_queries(np.array([[30.0, 4.0], [30.0, -4.0]]), np.zeros(2), segs)
    assert q["segment"].tolist() == [0, 0] and q["aligned"].tolist() == [True, True]


def test_lateral_offset_far_from_lanes_and_centering_clamp():
    segs, _ = _straight_lane()
    q = M.lane_queries(np.array([[30.0, 3.9], [30.0, 4.1], [-3.0, 0.0]]), np.zeros(3), segs)
    # the true distance, also beyond the 4 m search radius (no 10 m placeholder)
    np.testing.assert_allclose(q["lateral_offset"], [3.9, 4.1, 3.0], rtol=1e-6)
    assert q["aligned"].tolist() == [True, False, True] and q["segment"][1] == -1
    # lane_center clamps at a mean of 2 m: 1 m -> 0.5, 3.9 m and 10 m -> 0
    T = 5
    lat = np.array([[1.0] * T, [3.9] * T, [10.0] * T, [0.0] * T])
    m = M.metrics_from_steps(np.ones((4, T), bool), np.zeros((4, T)), np.zeros((4, T)),
                             np.zeros((4, T)), np.ones((4, T), bool), lat)
    np.testing.assert_allclose(m["lane_center"], [0.5, 0.0, 0.0, 1.0])


def test_hand_built_trajectory_end_to_end():
    """Drive 30 steps along the lane at 1 m offset, braking hard for the last 10."""
    dt = 0.1
    T = 30
    segs, _ = _straight_lane()
    v = np.concatenate([np.full(20, 10.0), 10.0 - 4.0 * dt * np.arange(1, 11)])  # a=-4 after 20
    x = 5.0 + np.concatenate([[0.0], np.cumsum(v[1:] * dt)])
    xy = np.stack([x, np.full(T, 1.0)], -1)
    heading = np.zeros(T)
    kin = M.kinematics_from_poses(xy, heading, dt)
    q = M.lane_queries(xy, heading, segs)
    m = M.metrics_from_steps(np.ones(T, bool), kin["a_long"], kin["a_lat"], kin["jerk"],
                             q["aligned"], q["lateral_offset"])
    np.testing.assert_allclose(kin["a_long"][21:], -4.0, atol=1e-6)
    np.testing.assert_allclose(kin["a_long"][:20], 0.0, atol=1e-6)
    # |a_long| > 3 on the 10 braking steps, a jerk spike of -40 at the onset step 20
    # whose a_long is 0 (kinematics put the first -4 at step 21)
    assert m["comfort_violations"] == 10 + 1
    assert m["comfort"] == pytest.approx(1 - 11 / 90)
    assert m["lane_align"] == 1.0
    assert m["lane_center"] == pytest.approx(0.5)
    s = M.task_score(True, False, False, m["comfort"], m["lane_align"], m["lane_center"])
    assert s == pytest.approx(100 * (0.2 * (1 - 11 / 90) + 0.5 + 0.3 * 0.5))


def test_lateral_kinematics_on_a_turn():
    """10 m/s straight for 5 steps, then turning at 0.5 rad/s: a_lat = 5 m/s^2 from the turn
    on, a lateral jerk of 5 / 0.1 = 50 m/s^3 at the onset, 0 elsewhere."""
    dt, T, v = 0.1, 12, 10.0
    heading = np.concatenate([np.zeros(5), 0.5 * dt * np.arange(1, T - 4)])
    mid = heading[:-1] + 0.5 * np.diff(heading)
    xy = np.concatenate([[[0.0, 0.0]], np.cumsum(v * dt * np.stack([np.cos(mid), np.sin(mid)], -1), 0)])
    kin = M.kinematics_from_poses(xy, heading, dt)
    np.testing.assert_allclose(kin["speed"], v, atol=1e-9)
    np.testing.assert_allclose(kin["a_lat"], [0.0] * 5 + [5.0] * (T - 5), atol=1e-9)
    np.testing.assert_allclose(kin["lat_jerk"], [0.0] * 5 + [50.0] + [0.0] * (T - 6), atol=1e-6)
    np.testing.assert_allclose(kin["a_long"], 0.0, atol=1e-9)


def test_accumulator_and_step_paths_agree():
    rng = np.random.default_rng(0)
    n, T = 64, 91
    alive = np.arange(T)[None] < rng.integers(1, T + 1, n)[:, None]
    args = (alive, rng.normal(0, 3, (n, T)), rng.normal(0, 3, (n, T)), rng.normal(0, 5, (n, T)),
            rng.random((n, T)) < 0.7, rng.exponential(1.5, (n, T)))
    a = M.metrics_from_steps(*args)
    b = M.metrics_from_accumulators(a["steps_alive"], a["comfort_violations"], a["aligned_steps"],
                                    a["lateral_offset_sum"])
    for k in ("comfort", "lane_align", "lane_center"):
        np.testing.assert_allclose(a[k], b[k])
        assert np.all((a[k] >= 0) & (a[k] <= 1))


def test_accumulators_clamp_and_zero_for_tasks_never_driven():
    # T = 2: 9 violations > 3 T clamp comfort at 0 (not -0.5); T = 0 gives 0 for all three
    m = M.metrics_from_accumulators([2, 0], [9, 0], [1, 0], [1.0, 0.0])
    np.testing.assert_allclose(m["comfort"], [0.0, 0.0])
    np.testing.assert_allclose(m["lane_align"], [0.5, 0.0])
    np.testing.assert_allclose(m["lane_center"], [0.75, 0.0])


def test_accumulators_reject_bad_input():
    with pytest.raises(ValueError, match="aligned_steps"):
        M.metrics_from_accumulators([5], [0], [6], [0.0])
    with pytest.raises(ValueError, match="steps_alive"):
        M.metrics_from_accumulators([np.nan], [0], [0], [0.0])
    for bad in (([-1], [0], [0], [0.0]), ([5], [-1], [0], [0.0]), ([5], [0], [-1], [0.0]), ([5], [0], [0], [-0.5])):
        with pytest.raises(ValueError, match="non-negative"):
            M.metrics_from_accumulators(*bad)


# ----------------------------------------------------------------------------- score
def test_score_zero_on_any_failure_and_formula_otherwise():
    goal = np.array([True, False, True, True, True])
    af = np.array([False, False, True, False, False])
    off = np.array([False, False, False, True, False])
    c = np.array([0.9, 1.0, 1.0, 1.0, 0.5])
    la = np.array([0.8, 1.0, 1.0, 1.0, 0.2])
    lc = np.array([0.7, 1.0, 1.0, 1.0, 0.0])
    s = M.task_score(goal, af, off, c, la, lc)
    assert s[1:4].tolist() == [0.0, 0.0, 0.0]
    assert s[0] == pytest.approx(100 * (0.2 * 0.9 + 0.5 * 0.8 + 0.3 * 0.7))
    assert s[4] == pytest.approx(100 * (0.2 * 0.5 + 0.5 * 0.2))
    assert M.task_score(True, False, False, 1.0, 1.0, 1.0) == pytest.approx(100.0)
    with pytest.raises(ValueError, match="lane_align"):
        M.task_score(True, False, False, 1.0, 1.5, 1.0)
    with pytest.raises(ValueError, match="comfort"):
        M.task_score(True, False, False, -0.1, 1.0, 1.0)


def _accumulators(**over):
    """sim.metrics-like accumulators of 6 egos driven for 10 steps each."""
    n = 6
    m = {"steps_alive": np.full(n, 10), "comfort_violations": np.full(n, 3), "aligned_steps": np.full(n, 8),
         "lateral_offset_sum": np.full(n, 5.0), "goal_step": np.full(n, -1), "first_collision_step": np.full(n, -1),
         "first_offroad_step": np.full(n, -1), "at_fault": np.zeros(n, bool)}
    m.update({k: np.asarray(v) for k, v in over.items()})
    return m


def test_episode_scores_events_from_the_accumulators():
    e = M.episode_scores(_accumulators(
        #               goal at 0 | goal + not-at-fault | goal + at-fault | off-road | at_fault w/o collision | timeout
        goal_step=[0, 40, 50, -1, 30, -1],
        first_collision_step=[-1, 20, 60, -1, -1, -1],
        at_fault=[False, False, True, False, True, False],
        first_offroad_step=[-1, -1, -1, 7, -1, -1],
    ))
    assert e["goal"].tolist() == [True, True, True, False, True, False]  # goal at decision 0 counts
    assert e["collision"].tolist() == [False, True, True, False, False, False]
    # at fault only with a collision: a stale at_fault flag alone is no collision
    assert e["at_fault_collision"].tolist() == [False, False, True, False, False, False]
    assert e["offroad"].tolist() == [False, False, False, True, False, False]
    # a timeout has none of the events (a collision without a goal is no timeout)
    assert e["timeout"].tolist() == [False, False, False, False, False, True]
    c = M.episode_scores(_accumulators(first_collision_step=[5, -1, -1, -1, -1, -1]))
    assert c["timeout"].tolist() == [False, True, True, True, True, True]
    # comfort 1 - 3/30, lane_align 8/10, lane_center 1 - (5/10)/2
    np.testing.assert_allclose(e["comfort"], 0.9)
    np.testing.assert_allclose(e["lane_align"], 0.8)
    np.testing.assert_allclose(e["lane_center"], 0.75)
    full = 100 * (0.2 * 0.9 + 0.5 * 0.8 + 0.3 * 0.75)
    # scored: goal without at-fault collision or off-road (a not-at-fault collision keeps the score)
    np.testing.assert_allclose(e["score"], [full, full, 0.0, 0.0, full, 0.0])


# ----------------------------------------------------------------------------- outcome classes
def test_outcome_class_priority():
    #            goal   at-fault  non-fault  offroad
    rows = [(True, True, False, True), (True, False, True, True), (True, False, True, False),
            (False, False, True, False), (False, False, False, False), (False, True, True, False)]
    g, af, nf, off = (np.array(c) for c in zip(*rows))
    cls = M.outcome_class(g, af, nf, off)
    C = M.OutcomeClass
    assert cls.tolist() == [C.AT_FAULT_COLLISION, C.OFFROAD, C.COMPLETED, C.NON_AT_FAULT_COLLISION,
                            C.TIMEOUT, C.AT_FAULT_COLLISION]


def test_repair_table_shares():
    C = M.OutcomeClass
    ref = np.array([C.TIMEOUT, C.TIMEOUT, C.TIMEOUT, C.COMPLETED, C.AT_FAULT_COLLISION])
    other = np.array([True, False, True, True, False])
    t = M.repair_table(ref, other)
    assert t["timeout"]["count"] == 3
    assert t["timeout"]["repaired"] == pytest.approx(2 / 3)
    assert t["completed"]["repaired"] == 1.0
    assert t["at_fault_collision"]["repaired"] == 0.0
    assert np.isnan(t["offroad"]["repaired"])
    assert sum(v["share"] for v in t.values()) == pytest.approx(1.0)
    assert all("harm" not in v for v in t.values())


def test_repair_is_goal_without_any_collision_or_offroad_harm_apart():
    #            goal   at-fault  non-fault  offroad  co-player harm
    rows = [(True, False, False, False, 0),   # repaired
            (True, False, False, False, 2),   # repaired: harm is not part of the definition
            (True, False, True, False, 0),    # not-at-fault collision: not a repair
            (True, True, False, False, 0),    # at-fault collision
            (True, False, False, True, 0),    # off-road
            (False, False, False, False, 0)]  # timeout
    g, af, nf, off, harm = (np.array(c) for c in zip(*rows))
    ok = M.repaired(g, af, nf, off)
    assert ok.tolist() == [True, True, False, False, False, False]
    C = M.OutcomeClass
    ref = np.full(len(rows), C.TIMEOUT)
    t = M.repair_table(ref, ok, harm)
    assert t["timeout"]["repaired"] == pytest.approx(2 / 6)
    assert t["timeout"]["harm"] == pytest.approx(1 / 6)   # its own column
    # one harmed co-player is harm already
    assert M.repair_table(ref, ok, np.array([1, 0, 0, 0, 0, 0]))["timeout"]["harm"] == pytest.approx(1 / 6)
    assert np.isnan(t["completed"]["harm"])
    with pytest.raises(ValueError, match="other_harm"):
        M.repair_table(ref, ok, harm[:3])


# ----------------------------------------------------------------------------- at fault
# The simulator's kernel is the one implementation (cpsim.kernels.geometry); the evaluation
# reads its at_fault flag. These hand-made cases pin BehaviorBench's rules on its NumPy
# reference (the kernel is checked against the same cases in tests/cpsim/test_sim_geometry.py).
def _v(speed, heading=0.0):
    return speed * np.array([np.cos(heading), np.sin(heading)])


def test_at_fault_rules_hand_made():
    G = pytest.importorskip("cpsim.kernels.geometry")
    K = G
    cases = [
        # (ego xy, heading, velocity), (other xy, velocity), other vulnerable, kind
        (((0, 0), 0.0, _v(0.0)), ((-4.8, 0), _v(5.0)), False, K.STOPPED_EGO),     # stopped ego
        (((0, 0), 0.0, _v(0.04)), ((4.8, 0), _v(5.0, np.pi)), False, K.STOPPED_EGO),  # 0.04 <= 0.05
        (((0, 0), 0.0, _v(5.0)), ((4.8, 0), _v(0.0)), False, K.STOPPED_TRACK),    # stopped other
        (((0, 0), 0.0, _v(2.0)), ((-5.0, 0.5), _v(8.0)), False, K.ACTIVE_REAR),   # from behind
        (((0, 0), 0.0, _v(8.0)), ((4.8, 0.5), _v(3.0)), False, K.ACTIVE_FRONT),   # closing 5 m/s
        (((0, 0), 0.0, _v(5.0)), ((4.5, 0), _v(4.6)), False, K.ACTIVE_LATERAL),   # closing 0.4 m/s
        (((0, 0), 0.0, _v(5.0)), ((2.0, 3.0), _v(9.0)), False, K.ACTIVE_LATERAL), # bearing 56 deg, closing < 0
        (((0, 0), 0.0, _v(5.0)), ((1.0, 2.0), _v(5.0, -0.3)), False, K.ACTIVE_LATERAL),  # 63 deg
        (((0, 0), 0.0, _v(5.0)), ((-1.0, -2.0), _v(5.0, 0.3)), False, K.ACTIVE_LATERAL),  # 117 deg
        (((0, 0), 0.0, _v(0.0)), ((1.0, 1.5), _v(1.0, -np.pi / 2)), True, K.VULNERABLE),  # pedestrian
    ]
    for (exy, eh, ev), (oxy, ov), vru, kind in cases:
        got = G.classify_collision(np.array(exy, float), eh, ev, np.array(oxy, float), ov, vru)
        assert got == kind, ((exy, oxy), G.COLLISION_KIND_NAMES[got])
    fault = {K.STOPPED_EGO: (False, False), K.STOPPED_TRACK: (True, True), K.ACTIVE_REAR: (False, True),
             K.ACTIVE_FRONT: (True, True), K.ACTIVE_LATERAL: (False, True), K.VULNERABLE: (True, True)}
    for kind, (plain, straddling) in fault.items():
        assert G.classify_fault(kind, False) == plain and G.classify_fault(kind, True) == straddling


def test_straddling_a_lane_divider():
    G = pytest.importorskip("cpsim.kernels.geometry")
    # two parallel lanes 3.6 m apart; a 2 m wide car reaches centrelines within 1 + 1.75 m
    pts = np.array([[0, 0], [100, 0], [0, 3.6], [100, 3.6]], np.float64)
    segs, ids = M.lane_segments(pts, np.array([0, 2, 4]), np.array([0, 0]))

    def straddles(ys, xs=(47.0, 48.0, 49.0, 50.0), heading=0.0, width=2.0):
        return G.straddles_divider_np(np.c_[xs, ys], heading, width, segs, ids)

    assert straddles([0.2, 0.4, 0.6, 0.9])          # drift 0.7 m, 2.7 m from lane 1 at the end
    assert not straddles([0.9, 0.9, 0.9, 0.9])      # near two lanes but no drift
    assert not straddles([0.6, 0.7, 0.8, 0.85])     # drift 0.25 <= 0.3
    assert not straddles([-0.6, -0.3, 0.0, 0.3])    # drift 0.9 m within one lane (3.3 m from lane 1)
    assert straddles([-0.6, -0.3, 0.0, 0.3], width=3.2)  # a wider box reaches 1.6 + 1.75 = 3.35 m
    assert straddles([0.0, 0.0, 0.0, 0.9])          # drift from the oldest to the newest position
    assert not straddles([0.0, 0.3, 0.6, 0.9], xs=(50.0, 50.0, 50.0, 50.0), heading=np.pi / 2)  # drift along


def test_summarize_rates():
    per = {"score": np.array([80.0, 0.0, 60.0, 0.0]), "goal": np.array([1, 0, 1, 0], bool),
           "at_fault_collision": np.array([0, 1, 0, 0], bool), "offroad": np.array([0, 0, 0, 1], bool),
           "co_player_harm": np.array([0, 2, 0, 0])}
    s = M.summarize(per)
    assert s == {"n": 4, "score": 35.0, "completion": 0.5, "at_fault_collision": 0.25,
                 "offroad": 0.25, "co_player_harm": 0.5}
    # completion is reaching the goal (also with an at-fault collision); optional keys are kept
    per.update(goal=np.array([1, 1, 1, 0], bool), timeout=np.array([0, 0, 0, 1], bool),
               non_at_fault_collision=np.array([0, 0, 1, 0], bool), comfort=np.array([1.0, 0.5, 0.5, 0.0]),
               lane_align=np.array([1.0, 1.0, 0.0, 0.0]), lane_center=np.array([0.2, 0.2, 0.2, 0.2]))
    s = M.summarize(per)
    assert s["completion"] == 0.75 and s["timeout"] == 0.25 and s["non_at_fault_collision"] == 0.25
    assert s["comfort"] == 0.5 and s["lane_align"] == 0.5 and s["lane_center"] == pytest.approx(0.2)
    # an empty group has no rates (nan), not zero rates
    e = M.summarize({k: np.zeros(0) for k in ("score", "goal", "at_fault_collision", "offroad", "timeout")})
    assert e["n"] == 0 and all(np.isnan(e[k]) for k in ("score", "completion", "offroad", "timeout"))
