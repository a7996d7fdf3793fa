"""Interactivity score and the Interactive-N / Random-N splits (cpsim.scenario.splits)."""

from __future__ import annotations

import dataclasses
import gzip
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import cpsim.scenario as cs
from cpsim.scenario import AgentType, RoadType, Scenario
from cpsim.scenario.splits import (
    interactive_split,
    interactivity_report,
    interactivity_score,
    interactivity_terms,
    random_split,
    track_tasks,
)

T = 91
DT = 0.1
LENGTH_2 = 5.0  # box length of the steering agent
YAW_STEP = 0.02  # rad per step of the steering agent while it turns


def hand_scenario(ego_goal_m: float = 30.0, sid: str = "hand") -> Scenario:
    """Six agents with closed-form interactivity terms (see test_score_matches_hand_computation).

    0 ego vehicle: x = t m, 10 m/s straight, valid throughout.
    1 vehicle: speed 5 + 0.01 t^2 (jerk exactly 2 m/s^3), 5 m ahead of the ego for t < 30.
    2 vehicle: 10 m/s, heading turns 0.02 rad/step until t = 45, then straight; 50 m away.
    3 pedestrian: erratic speed and heading (excluded from the kinematic terms), 3 m beside the ego.
    4 cyclist: 0.5 m/s (too slow for steering), heading noise, 10.5 m beside the ego (never near).
    5 vehicle: valid only from t = 50 (-10000 before), 8 m behind the ego.
    """
    rng = np.random.default_rng(0)
    n = 6
    t = np.arange(T, dtype=np.float64)
    ego_xy = np.stack([t * 1.0, np.zeros(T)], axis=-1)
    xy = np.zeros((n, T, 2))
    xy[0] = ego_xy
    xy[1] = ego_xy + np.where(t[:, None] < 30, [5.0, 0.0], [100.0, 0.0])
    xy[2] = ego_xy + [0.0, 50.0]
    xy[3] = ego_xy + [0.0, 3.0]
    xy[4] = ego_xy + [0.0, 10.5]
    xy[5] = ego_xy + [-8.0, 0.0]
    speed = np.zeros((n, T))
    speed[0] = 10.0
    speed[1] = 5.0 + 0.01 * t**2
    speed[2] = 10.0
    speed[3] = rng.uniform(0.0, 3.0, T)
    speed[4] = 0.5
    speed[5] = 10.0
    heading = np.zeros((n, T))
    heading[2] = YAW_STEP * np.minimum(t, 45)
    heading[3] = rng.uniform(-3.0, 3.0, T)
    heading[4] = rng.uniform(-0.5, 0.5, T)
    velocity = np.stack([speed * np.cos(heading), speed * np.sin(heading)], axis=-1)
    valid = np.ones((n, T), bool)
    valid[5, :50] = False
    for arr in (xy, velocity):
        arr[5, :50] = -10000.0
    heading[5, :50] = -10000.0
    goal = xy[:, 0] + np.array([[ego_goal_m, 0], [12, 0], [5, 0], [0, 20], [3, 0], [40, 0]], np.float64)
    sizes = np.tile([4.5, 2.0], (n, 1))
    sizes[2, 0] = LENGTH_2
    return Scenario(
        id=sid,
        log_xy=xy.astype(np.float32),
        log_heading=heading.astype(np.float32),
        log_velocity=velocity.astype(np.float32),
        log_valid=valid,
        goal_xy=goal.astype(np.float32),
        sizes=sizes.astype(np.float32),
        agent_types=np.array([0, 0, 0, AgentType.PEDESTRIAN, AgentType.CYCLIST, 0], np.int8),
        road_points=np.array([[0, -5], [100, -5]], np.float32),
        road_offsets=np.array([0, 2], np.int32),
        road_types=np.array([RoadType.ROAD_EDGE], np.int8),
        ego_index=0,
        family="test",
    )


def test_score_matches_hand_computation() -> None:
    s = hand_scenario()
    terms = interactivity_terms(s)
    assert terms.eligible and terms.reason == ""
    assert terms.agents_valid_t0 == 5
    # Goals >= 10 m among agents valid at t0: ego (30 m), agent 1 (12 m), agent 3 (20 m).
    assert terms.agents_far_goal == 3
    # Jerk samples: 89 per wheeled agent valid throughout (0, 1, 2, 4) + 39 for agent 5;
    # only agent 1 contributes, |jerk| = 2 m/s^3.
    mean_jerk = 89 * 2.0 / (4 * 89 + 39)
    assert terms.mean_abs_jerk == pytest.approx(mean_jerk, rel=2e-3)
    # Steering samples: agents 0, 1, 2 (89 each) + agent 5 (39); the cyclist is below 1 m/s.
    # Only agent 2's steering changes, once, from atan(0.6 L * 0.2 rad/s / 10 m/s) to 0.
    delta = math.atan(0.6 * LENGTH_2 * (YAW_STEP / DT) / 10.0)
    mean_steer = (delta / DT) / (3 * 89 + 39)
    assert terms.mean_abs_steer_rate == pytest.approx(mean_steer, rel=1e-4)
    # Neighbours within 10 m of the ego: agent 1 for 30 steps, the pedestrian for 91,
    # agent 5 for 41; the cyclist at 10.5 m never counts.
    mean_neighbours = (30 + 91 + 41) / 91
    assert terms.mean_neighbours == pytest.approx(mean_neighbours)
    assert terms.ego_goal_distance == pytest.approx(30.0)
    expected = (0.20 * min(3 / 15, 1) + 0.25 * min(mean_jerk / 30, 1) + 0.15 * min(mean_steer / 2, 1)
                + 0.20 * min(mean_neighbours / 3, 1) + 0.20 * min((30.0 - 10) / 40, 1))
    assert interactivity_score(s) == pytest.approx(expected, rel=1e-4)
    assert cs.interactivity_score is interactivity_score


def test_saturated_terms_cap_at_one() -> None:
    s = hand_scenario(ego_goal_m=200.0)
    t = interactivity_terms(s)
    assert t.ego_goal_distance == pytest.approx(200.0)
    low = interactivity_score(hand_scenario(ego_goal_m=50.0))  # (50 - 10) / 40 = 1: saturated
    assert interactivity_score(s) == pytest.approx(low)


def test_heading_wrap_is_not_steering() -> None:
    base = hand_scenario()
    heading = np.array(base.log_heading)
    # Ego drives straight along +-pi: raw differences jump by 2 pi, wrapped ones are ~0.
    heading[0] = np.where(np.arange(T) % 2 == 0, np.pi - 1e-3, -np.pi + 1e-3)
    velocity = np.array(base.log_velocity)
    velocity[0] = [-10.0, 0.0]
    wrapped = dataclasses.replace(base, log_heading=heading, log_velocity=velocity)
    assert interactivity_terms(wrapped).mean_abs_steer_rate == pytest.approx(
        interactivity_terms(base).mean_abs_steer_rate + 89 * 2 * math.atan(0.6 * 4.5 * 0.02 / 10) / DT / 306,
        rel=1e-3,
    )


@pytest.mark.parametrize("change, reason", [
    ("near_goal", "ego goal"),
    ("few_agents", "agents valid at t0"),
    ("ego_invalid", "ego is not valid at t0"),
])
def test_ineligible_tasks_get_none_not_zero(change: str, reason: str) -> None:
    s = hand_scenario()
    if change == "near_goal":
        s = hand_scenario(ego_goal_m=9.9)
    elif change == "few_agents":
        valid = np.array(s.log_valid)
        valid[4, 0] = False  # 4 agents valid at t0
        s = dataclasses.replace(s, log_valid=valid)
    else:
        valid = np.array(s.log_valid)
        valid[0, 0] = False
        s = dataclasses.replace(s, log_valid=valid)
    terms = interactivity_terms(s)
    assert not terms.eligible and reason in terms.reason
    assert interactivity_score(s) is None and terms.score is None
    assert terms.mean_neighbours >= 0.0  # terms are still reported


def test_exactly_ten_metres_is_eligible() -> None:
    assert interactivity_score(hand_scenario(ego_goal_m=10.0)) is not None


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_score_is_in_unit_interval_for_random_logs(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 12))
    valid = rng.random((n, T)) < 0.8
    valid[0, :] = True
    s = Scenario(
        id=f"r{seed}",
        log_xy=rng.normal(0, 20, (n, T, 2)).astype(np.float32),
        log_heading=rng.uniform(-10, 10, (n, T)).astype(np.float32),
        log_velocity=rng.normal(0, 15, (n, T, 2)).astype(np.float32),
        log_valid=valid,
        goal_xy=rng.normal(0, 60, (n, 2)).astype(np.float32),
        sizes=rng.uniform(0.5, 10, (n, 2)).astype(np.float32),
        agent_types=rng.integers(0, 4, n).astype(np.int8),
        road_points=np.zeros((1, 2), np.float32),
        road_offsets=np.array([0, 1], np.int32),
        road_types=np.array([RoadType.STOP_SIGN], np.int8),
        ego_index=0,
    )
    terms = interactivity_terms(s)
    assert (terms.score is None) == (not terms.eligible)
    if terms.score is not None:
        assert 0.0 <= terms.score <= 1.0
    for value in (terms.mean_abs_jerk, terms.mean_abs_steer_rate, terms.mean_neighbours):
        assert np.isfinite(value) and value >= 0.0


# ----------------------------------------------------------------------------- splits
def pool() -> list[Scenario]:
    """Scenarios whose scores grow with the ego goal distance; one ineligible, one tie."""
    goals = {"g15": 15.0, "g35": 35.0, "g20": 20.0, "near": 5.0, "g30": 30.0, "g25b": 25.0, "g25a": 25.0}
    return [hand_scenario(ego_goal_m=d, sid=sid) for sid, d in goals.items()]


def test_interactive_split_picks_top_scores_with_id_tiebreak() -> None:
    scenarios = pool()
    top = interactive_split(scenarios, 4)
    assert [s.id for s in top] == ["g35", "g30", "g25a", "g25b"]
    scores = [interactivity_score(s) for s in top]
    assert scores == sorted(scores, reverse=True)
    assert [s.id for s in interactive_split(scenarios, 6)] == ["g35", "g30", "g25a", "g25b", "g20", "g15"]
    assert interactive_split(scenarios, 0) == []
    assert [s.id for s in interactive_split(list(reversed(scenarios)), 4)] == ["g35", "g30", "g25a", "g25b"]


def test_split_argument_errors() -> None:
    scenarios = pool()
    with pytest.raises(ValueError, match="n: 7 exceeds the 6 eligible"):
        interactive_split(scenarios, 7)
    with pytest.raises(ValueError, match="scenarios: empty"):
        interactive_split([], 1)
    with pytest.raises(ValueError, match="scenarios: empty"):
        random_split([], 1, seed=0)
    with pytest.raises(ValueError, match="n: 8 exceeds"):
        random_split(scenarios, 8, seed=0)
    with pytest.raises(ValueError, match="n: 7 exceeds the 6 eligible"):
        random_split(scenarios, 7, seed=0, eligible_only=True)
    with pytest.raises(ValueError, match="n: expected a non-negative integer"):
        random_split(scenarios, -1, seed=0)
    with pytest.raises(ValueError, match="n: expected"):
        interactive_split(scenarios, 2.0)  # type: ignore[arg-type]


def test_random_split_is_seeded_uniform_and_nested() -> None:
    scenarios = [hand_scenario(sid=f"s{i:02d}") for i in range(20)]
    a = random_split(scenarios, 8, seed=3)
    assert [s.id for s in a] == [s.id for s in random_split(scenarios, 8, seed=3)]
    assert len(a) == 8 and len({s.id for s in a}) == 8
    assert [s.id for s in random_split(scenarios, 5, seed=3)] == [s.id for s in a[:5]]
    others = {tuple(s.id for s in random_split(scenarios, 8, seed=k)) for k in range(4, 9)}
    assert len(others | {tuple(s.id for s in a)}) > 1  # the seed matters
    # Uniform: over many seeds every scenario is drawn about n / N of the time.
    counts = np.zeros(20)
    for seed in range(400):
        for s in random_split(scenarios, 5, seed=seed):
            counts[int(s.id[1:])] += 1
    assert np.all(np.abs(counts / 400 - 0.25) < 0.1)
    eligible = random_split(pool(), 6, seed=1, eligible_only=True)
    assert "near" not in {s.id for s in eligible}


def test_report_lists_every_scenario_in_order() -> None:
    scenarios = pool()
    report = interactivity_report(scenarios)
    assert [r.scenario_id for r in report] == [s.id for s in scenarios]
    by_id = {r.scenario_id: r for r in report}
    assert not by_id["near"].eligible and by_id["near"].score is None
    assert by_id["g35"].as_dict()["score"] == pytest.approx(interactivity_score(scenarios[1]))


# ----------------------------------------------------------------------------- WOMD tasks and folders
def test_track_tasks_one_task_per_vehicle_track() -> None:
    base = dataclasses.replace(hand_scenario(sid="scene"), tracks_to_predict=np.array([2, 0, 3, 2, 1], np.int32))
    tasks = track_tasks([base])
    assert [t.ego_index for t in tasks] == [2, 0, 1]  # pedestrian 3 left out, repeated 2 once
    assert all(t.id == "scene" and t.source == base.source for t in tasks)
    assert tasks[1] is base  # its own ego: the scenario itself
    assert tasks[0].log_xy is base.log_xy  # arrays shared, not copied
    assert [t.ego_index for t in track_tasks([base], vehicles_only=False)] == [2, 0, 3, 1]
    no_tracks = hand_scenario(sid="procedural-like")
    assert track_tasks([no_tracks]) == [no_tracks]
    walkers = dataclasses.replace(base, tracks_to_predict=np.array([3], np.int32))
    assert track_tasks([walkers]) == []
    with pytest.raises(ValueError, match=r"scenarios\[0\]: expected a Scenario"):
        track_tasks(["not a scenario"])  # type: ignore[list-item]


def scenario_doc(s: Scenario) -> dict:
    """A Scenario as a GPUDrive / PufferDrive JSON document (the fields the loader reads)."""
    kinds = {0: "vehicle", 1: "pedestrian", 2: "cyclist", 3: "other"}
    objects = [{
        "position": [{"x": float(x), "y": float(y), "z": 0.0} for x, y in s.log_xy[i]],
        "velocity": [{"x": float(x), "y": float(y)} for x, y in s.log_velocity[i]],
        "heading": [float(h) for h in s.log_heading[i]],
        "valid": [bool(v) for v in s.log_valid[i]],
        "length": float(s.sizes[i, 0]), "width": float(s.sizes[i, 1]),
        "goalPosition": {"x": float(s.goal_xy[i, 0]), "y": float(s.goal_xy[i, 1]), "z": 0.0},
        "type": kinds[int(s.agent_types[i])], "id": 1000 + i,
    } for i in range(s.num_agents)]
    roads = [{"geometry": [{"x": float(x), "y": float(y), "z": 0.0} for x, y in s.road(r)], "type": "road_edge"}
             for r in range(s.num_roads)]
    return {"scenario_id": s.id, "objects": objects, "roads": roads,
            "metadata": {"sdc_track_index": int(s.ego_index),
                         "tracks_to_predict": [{"track_index": int(k), "difficulty": 0} for k in s.tracks_to_predict]}}


def womd_folder(path: Path) -> Path:
    """Four .json.gz scenes, tracks_to_predict [0, 1, 2, 3]: egos 0 (goal varies) and 1 (12 m)
    can be eligible, ego 2 (goal 5 m) never, agent 3 is a pedestrian (no task)."""
    path.mkdir()
    for sid, goal in (("w15", 15.0), ("w35", 35.0), ("w25", 25.0), ("w05", 5.0)):
        s = dataclasses.replace(hand_scenario(ego_goal_m=goal, sid=sid),
                                tracks_to_predict=np.array([0, 1, 2, 3], np.int32))
        (path / f"{sid}.json.gz").write_bytes(gzip.compress(json.dumps(scenario_doc(s)).encode()))
    return path


def _keys(tasks: list[Scenario]) -> list[tuple[str, int]]:
    return [(t.id, t.ego_index) for t in tasks]


def test_interactive_split_of_a_folder_ranks_its_track_tasks(tmp_path: Path) -> None:
    folder = womd_folder(tmp_path / "womd")
    tasks = track_tasks(cs.load_dir(folder)[0])
    assert len(tasks) == 12  # 4 scenes x 3 vehicle tracks
    eligible = [t for t, r in zip(tasks, interactivity_report(tasks)) if r.eligible]
    assert sorted(_keys(eligible)) == sorted([(sid, 0) for sid in ("w15", "w25", "w35")]
                                             + [(sid, 1) for sid in ("w05", "w15", "w25", "w35")])
    top = interactive_split(folder, 7)
    assert _keys(top) == _keys(interactive_split(tasks, 7))
    scores = [interactivity_score(t) for t in top]
    assert None not in scores and scores == sorted(scores, reverse=True)
    assert _keys(top)[0] == ("w35", 0)  # the farthest ego goal scores highest
    assert cs.interactive_split is interactive_split and cs.track_tasks is track_tasks
    with pytest.raises(ValueError, match="n: 8 exceeds the 7 eligible tasks"):
        interactive_split(folder, 8)
    # the .npz cache is used when asked for
    assert _keys(interactive_split(folder, 3, cache_dir=tmp_path / "cache")) == _keys(top[:3])
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["w05.npz", "w15.npz", "w25.npz", "w35.npz"]
    with pytest.raises(ValueError, match="cache_dir: only used when the source is a folder"):
        interactive_split(tasks, 1, cache_dir=tmp_path / "cache")
    with pytest.raises(ValueError, match="folder does not exist"):
        interactive_split(tmp_path / "missing", 1)


def test_random_split_of_a_folder_samples_eligible_tasks(tmp_path: Path) -> None:
    folder = womd_folder(tmp_path / "womd")
    tasks = track_tasks(cs.load_dir(folder)[0])
    a = random_split(folder, 5, seed=3)
    assert _keys(a) == _keys(random_split(str(folder), 5, seed=3))  # str or Path
    assert _keys(a) == _keys(random_split(tasks, 5, seed=3, eligible_only=True))
    assert all(interactivity_score(t) is not None for t in a)
    assert len(set(_keys(a))) == 5
    assert _keys(random_split(folder, 3, seed=3)) == _keys(a)[:3]  # nested
    assert {tuple(_keys(random_split(folder, 5, seed=k))) for k in range(6)} != {tuple(_keys(a))}
    everything = random_split(folder, 12, seed=0, eligible_only=False)  # opt out: all 12 tasks
    assert sorted(_keys(everything)) == sorted(_keys(tasks))
    with pytest.raises(ValueError, match="n: 8 exceeds the 7 eligible tasks"):
        random_split(folder, 8, seed=0)


# ----------------------------------------------------------------------------- real WOMD validation scenes
def _womd_valid() -> Path:
    env = os.environ.get("CPSIM_WOMD_DIR")
    return (Path(env) if env else Path(__file__).resolve().parents[2].parent / "shared/data/womd") / "valid"


WOMD_VALID = _womd_valid()


@pytest.mark.skipif(not WOMD_VALID.is_dir(), reason=f"{WOMD_VALID} not found (set CPSIM_WOMD_DIR)")
def test_splits_of_the_real_validation_scenes() -> None:
    scenes = cs.load_dir(WOMD_VALID)[0]
    tasks = track_tasks(scenes)
    vehicle_tracks = sum(int((s.agent_types[np.unique(s.tracks_to_predict)] == AgentType.VEHICLE).sum())
                         for s in scenes)
    assert len(scenes) == 100 and len(tasks) == vehicle_tracks == 245
    assert len(set(_keys(tasks))) == len(tasks)
    top = interactive_split(tasks, 20)
    scores = [interactivity_score(t) for t in top]
    assert None not in scores and scores == sorted(scores, reverse=True)
    for t in top:  # BehaviorBench eligibility, checked from the data
        assert t.ego_index in t.tracks_to_predict and t.agent_types[t.ego_index] == AgentType.VEHICLE
        assert t.log_valid[t.ego_index, 0] and t.log_valid[:, 0].sum() >= 5
        assert np.linalg.norm(t.goal_xy[t.ego_index] - t.log_xy[t.ego_index, 0]) >= 10.0
    rand = random_split(tasks, 20, seed=0, eligible_only=True)
    assert all(interactivity_score(t) is not None for t in rand) and len(set(_keys(rand))) == 20
    assert _keys(rand) == _keys(random_split(tasks, 20, seed=0, eligible_only=True))
