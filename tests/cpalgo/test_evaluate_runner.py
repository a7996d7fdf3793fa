"""The batched evaluation runner end to end on small procedural tasks (CPU simulator)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("cpsim.simulator")

from cpalgo.evaluate import metrics as M  # noqa: E402
from cpalgo.evaluate import runner as R  # noqa: E402

N_TASKS = 4  # per split


@pytest.fixture(scope="module")
def tasks():
    return R.make_tasks("procedural", "both", N_TASKS, seed=0)


@pytest.fixture(scope="module")
def expert(tasks):
    """Expert log replay as the ego under replay and IDM traffic, every episode recorded."""
    ev = R.Evaluator(tasks, ["replay", "idm"], config=R.EvalConfig(progress=False, max_worlds=64,
                                                                    record=tuple(range(4 * N_TASKS))))
    return ev, ev.run("expert")


def log_reaches_goal(sc, radius: float = 2.0, max_speed: float = 20.0) -> bool:
    """Whether the ego's own log passes its goal test (procedural egos whose logged driver
    stopped short get a goal further along the route, which replay cannot reach)."""
    e = sc.ego_index
    d = np.linalg.norm(sc.log_xy[e] - sc.goal_xy[e], axis=-1)
    return bool(np.any(sc.log_valid[e] & (d < radius) & (sc.log_speed[e] <= max_speed)))


def test_expert_replay_completes_with_high_score(expert):
    ev, res = expert
    c = res.columns
    assert res.num_rows == 2 * 2 * N_TASKS
    rep = c["regime"] == "replay"
    reach = np.array([log_reaches_goal(next(s for s in ev.scenarios if s.id == sid)) for sid in c["scenario_id"]])
    assert reach.any()
    # the logs are collision-free: the replayed expert completes every task its log completes
    assert np.array_equal(c["goal"][rep], reach[rep])
    assert c["score"][rep & reach].mean() >= 90.0
    assert not (c["at_fault_collision"] | c["offroad"])[rep].any()
    # the score column is the formula applied to the per-task metrics
    want = M.task_score(c["goal"], c["at_fault_collision"], c["offroad"], c["comfort"], c["lane_align"],
                        c["lane_center"])
    np.testing.assert_allclose(c["score"], want)
    # exactly one outcome class per row, consistent with the flags
    cls = c["outcome_class"]
    assert np.array_equal(cls == M.OutcomeClass.COMPLETED, c["goal"] & ~c["at_fault_collision"] & ~c["offroad"])


def test_teacher_ego_drives_like_its_teacher(expert):
    """``reactive`` / ``tracking`` as the ego: the imitation teacher drives slot 0 under the
    deployment condition (a reference row for a student policy)."""
    ev, res_replay = expert
    res = ev.run("tracking")
    assert res.label == "tracking-teacher" and res.checkpoint == "teacher:tracking"
    c = res.columns
    rep = c["regime"] == "replay"
    # the tracking teacher follows the ego's log: under replay traffic it stays on the road
    # and completes (nearly) what the replayed log completes
    assert not c["offroad"][rep].any()
    assert c["goal"][rep].sum() >= max(1, res_replay.columns["goal"][rep].sum() - 1)
    reactive = ev.run("reactive", label="teacher")
    assert reactive.label == "teacher"
    assert not np.array_equal(reactive.columns["steps_alive"], np.zeros_like(reactive.columns["steps_alive"]))
    # act() is the teacher's slot-0 action on the bound simulator
    ego = R.TeacherEgo("reactive")
    with pytest.raises(RuntimeError, match="bind"):
        ego.act(np.zeros((1, 4), np.float32), np.ones(1, bool))
    ev.sim.reset(scenario_index=np.zeros(ev.num_worlds, np.int64))
    ego.bind(ev.sim)
    from cpsim.arrays import to_numpy
    from cpsim.expert import ReactiveExpert

    np.testing.assert_array_equal(ego.act(np.zeros((ev.num_worlds, 4), np.float32), np.ones(ev.num_worlds, bool)),
                                  to_numpy(ReactiveExpert(ev.sim).actions())[:, 0])
    with pytest.raises(ValueError, match="teacher"):
        R.TeacherEgo("oracle")


class Weave:
    """Open-loop ego: constant speed, lateral jerk switching every few steps (drifts off the
    lane centre and out of alignment, so the lane metrics are not trivially 1)."""

    def __init__(self, period: int = 6):
        self.period, self.t = period, 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        lat = 2 if (self.t // self.period) % 2 == 0 else 0  # +4 / -4 m/s^3
        self.t += 1
        return np.full(obs.shape[0], 2 * 3 + lat)  # long jerk 0


def _scenario_of(ev, sid):
    return next(s for s in ev.scenarios if s.id == sid)


def test_accumulators_match_recorded_trajectory(expert, tasks):
    """steps_alive and the lane metrics from the simulator's accumulators agree with the
    NumPy reference recomputed from the recorded ego trajectory (expert and weaving ego)."""
    ev, res_expert = expert
    res_weave = ev.run(Weave(), label="weave")
    checked = 0
    spread = []
    for res in (res_expert, res_weave):
        for row, traj in res.trajectories.items():
            sc = _scenario_of(ev, res.columns["scenario_id"][row])
            alive = traj["alive"][0]
            # recorded index k = state after k steps; an agent removed at step k still has
            # its step counted
            t = np.arange(1, alive.size)[alive[:-1]]
            assert int(res.columns["steps_alive"][row]) == t.size
            segs, _ = M.lane_segments(sc.road_points, sc.road_offsets, sc.road_types)
            q = M.lane_queries(traj["xy"][0, t], traj["heading"][0, t], segs)
            ref = M.metrics_from_accumulators(t.size, 0, q["aligned"].sum(), q["lateral_offset"].sum())
            # the simulator simplifies road polylines (5 cm chord tolerance): a step right at
            # the 15 degree or 4 m boundary may flip
            assert res.columns["lane_center"][row] == pytest.approx(ref["lane_center"], abs=0.03)
            aligned_sim = round(res.columns["lane_align"][row] * t.size)
            assert abs(aligned_sim - q["aligned"].sum()) <= max(1, 0.03 * t.size)
            spread.append(ref["lane_center"])
            checked += 1
    assert checked == 2 * res_expert.num_rows
    assert min(spread) < 0.8  # the weaving ego really left the lane centre


def test_at_fault_flags_match_reference_rules(expert):
    """Every ego collision: the simulator's at_fault equals BehaviorBench's rules (the NumPy
    reference of the kernel, ``cpsim.kernels.geometry``) applied to the recorded state one
    step before contact and the ego's last four positions."""
    from cpsim.kernels import geometry as G

    ev, _ = expert
    scale = ev.sim.config.box_scale
    kinds = []
    for action in (10, 7):  # accelerate straight (+4 / 0 long jerk... index long*3 + lat)
        res = ev.run(lambda obs, a=action: np.full(obs.shape[0], a), label=f"a{action}")
        c = res.columns
        for row, tr in res.trajectories.items():
            k = int(c["collision_step"][row])
            if k < 0:
                continue
            j = int(c["collision_partner"][row])
            sc = _scenario_of(ev, c["scenario_id"][row])
            assert (sc.agent_types == 0).all()  # procedural scenes: vehicles only
            kind = G.classify_collision(tr["xy"][0, k - 1], tr["heading"][0, k - 1], tr["velocity"][0, k - 1],
                                        tr["xy"][j, k - 1], tr["velocity"][j, k - 1])
            segs, ids = M.lane_segments(sc.road_points, sc.road_offsets, sc.road_types)
            past = tr["xy"][0, np.maximum(np.arange(k - 4, k), 0)]
            straddled = G.straddles_divider_np(past, tr["heading"][0, k - 1], tr["sizes"][0][1] * scale,
                                               segs, ids, ev.sim.config.lane_radius)
            assert G.classify_fault(kind, straddled) == bool(c["at_fault_collision"][row]), (row, kind)
            kinds.append(int(kind))
    assert len(kinds) >= 3


def test_policy_ego_batched_over_regimes(tasks):
    """A callable ego (always 'keep accelerating straight') under two regimes: one
    simulator for every task-regime; crashes are classified and scored 0."""
    import cpsim

    ev = R.Evaluator(tasks[:N_TASKS], ["replay", "static"], config=R.EvalConfig(progress=False, max_worlds=5))
    assert ev.num_worlds == 5 and ev.num_rows == 2 * N_TASKS  # two chunks, the last one padded
    n_act = cpsim.SimConfig().num_actions
    full_throttle = n_act - 2  # jerk set: long +4, lat 0
    res = ev.run(lambda obs: np.full(obs.shape[0], full_throttle), label="throttle")
    c = res.columns
    failed = ~c["goal"]
    assert np.all(c["score"][failed] == 0)
    assert np.all(c["goal"] | c["at_fault_collision"] | c["non_at_fault_collision"] | c["offroad"] | c["timeout"])
    assert res.meta["task_regimes_per_second"] > 0


def test_bad_inputs(tasks, tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="unknown regime"):
        R.Evaluator(tasks, ["replay", "rush-hour"])
    assert R.Evaluator(tasks[:1], "idm").regimes == ["idm"]  # one name, not its letters
    with pytest.raises(ValueError, match="must return 1 integer actions"):
        R.Evaluator(tasks[:1], ["idm"], config=R.EvalConfig(progress=False)).run(lambda obs: np.zeros(3))
    # without the shipped anchor, the policy regimes need an explicit co-player policy
    monkeypatch.setattr(R, "DEFAULT_TRAFFIC_PATHS", {"classic": tmp_path / "no-anchor.zip", "jerk": tmp_path / "no.zip"})
    with pytest.raises(ValueError, match="traffic_policy"):
        R.Evaluator(tasks, ["normal"])
    with pytest.raises(ValueError, match="profile"):
        R.Evaluator(tasks, ["replay"], config=R.EvalConfig(deploy_condition="reckless"))
    with pytest.raises(ValueError, match="tasks"):
        R.Evaluator([], ["replay"])

    class WrongSize:
        observation_space = type("S", (), {"shape": (7,)})()

        def predict(self, obs, state=None, episode_start=None, deterministic=True):
            return np.zeros(len(obs), np.int64), None

    ev = R.Evaluator(tasks[:1], ["replay"], config=R.EvalConfig(progress=False))
    with pytest.raises(ValueError, match="observation size 7"):
        ev.run(WrongSize())
    # an Interactive split with no eligible task (every goal 1 m from its start) is an error
    import dataclasses

    near = [dataclasses.replace(t.scenario, goal_xy=t.scenario.log_xy[:, 0] + 1.0) for t in tasks[:2]]
    with pytest.raises(ValueError, match="interactive split .* is empty"):
        R.make_tasks(near, "interactive", 3)


def test_cli_bad_checkpoint_leaves_no_results(tmp_path, capsys):
    from cpalgo.evaluate.__main__ import main

    bad = tmp_path / "broken.zip"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    out = tmp_path / "res"
    assert main(["--policy", str(bad), "--regimes", "replay", "--n", "2", "--out", str(out),
                 "--no-progress"]) == 2
    assert "broken.zip" in capsys.readouterr().err
    assert not out.exists()
    assert main(["--policy", "expert", "--split", "sideways", "--out", str(out)]) == 2
    assert not out.exists()


def test_cli_writes_results(tmp_path):
    from cpalgo.evaluate.__main__ import main

    out = tmp_path / "res"
    rc = main(["--policy", "expert", "--policy", "idm", "--regimes", "replay,idm", "--split", "random",
               "--n", "2", "--out", str(out), "--no-progress", "--record", "1"])
    assert rc == 0
    names = {p.name for p in out.iterdir()}
    assert {"summary.json", "tables.md", "tasks.csv", "scores_random.png", "outcomes.png"} <= names
    md = (out / "tables.md").read_text()
    assert "| expert-replay |" in md and "| idm |" in md


def test_sb3_checkpoint_ego_and_traffic_in_every_regime(tasks, tmp_path):
    """A saved RecurrentPPO checkpoint as ego and as co-player policy, a BC checkpoint for
    the log-imitation regime: all eight regimes in one run, deterministic across runs."""
    from sb3_contrib import RecurrentPPO

    from cpalgo.traffic.bc import BCPolicy
    from cpsim.envs.selfplay import SelfPlayVecEnv

    env = SelfPlayVecEnv([tasks[0].scenario], num_worlds=1, max_agents=4)
    model = RecurrentPPO("MlpLstmPolicy", env, n_steps=8, seed=0,
                         policy_kwargs=dict(lstm_hidden_size=16, net_arch=[16]))
    anchor = tmp_path / "anchor.zip"
    model.save(anchor)
    layout = env.obs_layout
    bc = BCPolicy(layout.size, env.action_space.n, (16,), (layout.condition.start, layout.condition.stop))
    bc_path = bc.save(tmp_path / "bc.pt")
    two = [tasks[0], tasks[N_TASKS]]  # one task of each split
    import torch

    threads = torch.get_num_threads()
    runs = [R.evaluate(str(anchor), two, R.REGIMES, traffic_policy=str(anchor), bc_policy=bc_path,
                       progress=False, max_worlds=8) for _ in range(2)]
    assert torch.get_num_threads() == threads  # EvalConfig.torch_threads is restored
    c = runs[0].columns
    assert runs[0].num_rows == 2 * len(R.REGIMES)
    assert set(c["regime"]) == set(R.REGIMES) and set(c["split"]) == {"interactive", "random"}
    for k in ("goal", "at_fault_collision", "offroad", "score", "co_player_harm", "steps_alive"):
        np.testing.assert_array_equal(c[k], runs[1].columns[k])
    assert np.all((c["steps_alive"] >= 1) & (c["steps_alive"] <= 91))
    # a BC checkpoint whose observation size does not match is refused up front
    small = BCPolicy(layout.size - 3, env.action_space.n, (8,)).save(tmp_path / "small.pt")
    with pytest.raises(ValueError, match="bc_policy: observation size"):
        R.Evaluator(two, ["bc"], bc_policy=small)


def test_selfplay_regime_uses_the_separate_ppo_policy(tasks, tmp_path, monkeypatch):
    """The PPO column is a separately trained policy under the normal profile; without one
    the anchor (traffic policy) under p_train conditions stands in."""
    import cpsim

    class Policy:
        observation_space = None

        def predict(self, obs, state=None, episode_start=None, deterministic=True):
            return np.zeros(len(obs), np.int64), None

    anchor, ppo = Policy(), Policy()
    ev = R.Evaluator(tasks[:1], ["selfplay", "normal"], traffic_policy=anchor, ppo_policy=ppo,
                     config=R.EvalConfig(progress=False))
    sp = ev._drivers["selfplay"]
    assert sp.model is ppo and np.array_equal(sp.condition, cpsim.profile("normal"))
    assert ev._drivers["normal"].model is anchor
    monkeypatch.setattr(R, "DEFAULT_PPO_PATHS", {"classic": tmp_path / "no-ppo.zip", "jerk": tmp_path / "no-ppo.zip"})
    ev = R.Evaluator(tasks[:1], ["selfplay"], traffic_policy=anchor, config=R.EvalConfig(progress=False))
    assert ev._drivers["selfplay"].model is anchor and ev._drivers["selfplay"].condition is None
    with pytest.raises(ValueError, match="ppo_policy: checkpoint"):
        R.Evaluator(tasks[:1], ["selfplay"], ppo_policy=tmp_path / "missing.zip")


# ----------------------------------------------------------------------------- co-players
def with_extra_agents(sc, parked: int, sid: str):
    """``sc`` plus ``parked`` parked vehicles (goal = their t0 position) in a row 300 m away,
    one pedestrian present at t0 and one vehicle that appears at t = 10 (no slot)."""
    import dataclasses

    from cpsim.scenario import AgentType

    T = sc.num_steps
    k = parked + 2
    base = sc.log_xy[sc.ego_index, 0] + np.array([0.0, 300.0], np.float32)
    xy0 = base + np.stack([6.0 * np.arange(k), np.zeros(k)], -1).astype(np.float32)
    valid = np.ones((k, T), bool)
    valid[-1, :10] = False
    types = np.array([AgentType.VEHICLE] * parked + [AgentType.PEDESTRIAN, AgentType.VEHICLE], np.int8)
    extra = {
        "log_xy": np.concatenate([sc.log_xy, np.repeat(xy0[:, None], T, 1)]),
        "log_heading": np.concatenate([sc.log_heading, np.zeros((k, T), np.float32)]),
        "log_velocity": np.concatenate([sc.log_velocity, np.zeros((k, T, 2), np.float32)]),
        "log_valid": np.concatenate([sc.log_valid, valid]),
        "goal_xy": np.concatenate([sc.goal_xy, xy0]),
        "sizes": np.concatenate([sc.sizes, np.tile(np.array([[4.5, 2.0]], np.float32), (k, 1))]),
        "agent_types": np.concatenate([sc.agent_types, types]),
    }
    if sc.mark_as_expert is not None:
        extra["mark_as_expert"] = np.concatenate([sc.mark_as_expert, np.zeros(k, bool)])
    if sc.agent_ids is not None:
        extra["agent_ids"] = np.concatenate([sc.agent_ids, sc.agent_ids.max() + 1 + np.arange(k)])
    return dataclasses.replace(sc, id=sid, **extra)


def test_slots_hold_every_agent_present_at_t0_up_to_128(tasks):
    """Slots: every agent present at t0 (not every agent of the log), up to BehaviorBench's 128."""
    sc = tasks[0].scenario
    mid = with_extra_agents(sc, 70, "seventy")  # more than the old cap of 64
    n0 = int(mid.log_valid[:, 0].sum())
    assert n0 > 64 and mid.num_agents > n0  # agents absent at t0 (the late vehicle...) get no slot
    ev = R.Evaluator([R.Task("random", 0, mid)], ["replay"], config=R.EvalConfig(progress=False))
    assert ev.sim.max_agents == n0
    assert int((ev.sim.agent_index.numpy()[0] >= 0).sum()) == n0
    big = with_extra_agents(sc, 140, "many")
    ev = R.Evaluator([R.Task("random", 0, mid), R.Task("random", 1, big)], ["replay"],
                     config=R.EvalConfig(progress=False, max_worlds=2))
    assert R.MAX_EVAL_AGENTS == 128 and ev.sim.max_agents == 128
    ev.sim.reset(scenario_index=np.array([1, 0]))
    slots = ev.sim.agent_index.numpy()
    assert (slots[0] >= 0).all() and int((slots[1] >= 0).sum()) == n0
    assert R.Evaluator(tasks[:1], ["replay"], config=R.EvalConfig(progress=False, max_agents=8)).sim.max_agents == 8


@pytest.mark.parametrize("rule", ["controllable", "vehicles"])
def test_coplayer_rule_decides_who_follows_the_regime(tasks, rule):
    """``controllable``: controllable vehicles follow the regime, parked ones replay;
    ``vehicles`` (BehaviorBench): every vehicle present at t0 but the ego; pedestrians
    replay under both; the ego slot is never a co-player."""
    from cpsim.config import Controller
    from cpsim.scenario import AgentType

    sc = with_extra_agents(tasks[0].scenario, 5, "parked")
    ev = R.Evaluator([R.Task("random", 0, sc)], ["idm"], config=R.EvalConfig(progress=False, coplayers=rule))
    ev.sim.reset(scenario_index=np.array([0]))
    drv = ev._drivers["idm"]
    assert drv.coplayers == rule
    drv.assign(ev.sim, np.array([0]))
    idx = ev.sim.agent_index.numpy()[0]
    ctrl = ev.sim.controllers.numpy()[0]
    ok = idx >= 0
    vehicle = np.zeros(idx.size, bool)
    vehicle[ok] = sc.agent_types[idx[ok]] == AgentType.VEHICLE
    controllable = np.zeros(idx.size, bool)
    controllable[ok] = sc.controllable[idx[ok]]
    follows = (vehicle if rule == "vehicles" else controllable).copy()
    follows[0] = False  # the ego slot
    assert idx[0] == sc.ego_index
    assert (ctrl[follows] == int(Controller.IDM)).all()
    assert (ctrl[ok & ~follows][1:] == int(Controller.REPLAY)).all()
    parked = vehicle & ~controllable
    parked[0] = False
    assert parked.sum() >= 5 and (vehicle & ~follows)[1:].any() == (rule == "controllable")
    assert (ctrl[parked] == (int(Controller.IDM) if rule == "vehicles" else int(Controller.REPLAY))).all()
    with pytest.raises(ValueError, match="coplayers"):
        R.EvalConfig(coplayers="everyone")


def test_parked_coplayers_stay_in_the_scene_without_a_goal(tasks):
    """``vehicles``: a parked vehicle starts inside its 2 m evaluation goal radius. It has no
    task, so the simulator never scores it as arrived: under IDM it stays parked and present
    for the whole episode instead of leaving the scene on its first step."""
    sc = with_extra_agents(tasks[0].scenario, 5, "parked")
    ev = R.Evaluator([R.Task("random", 0, sc)], ["idm"], config=R.EvalConfig(progress=False, coplayers="vehicles"))
    ev.sim.reset(scenario_index=np.array([0]))
    ev._drivers["idm"].assign(ev.sim, np.array([0]))
    idx = ev.sim.agent_index.numpy()[0]
    parked = np.zeros(idx.size, bool)
    parked[idx >= 0] = idx[idx >= 0] >= tasks[0].scenario.num_agents
    parked &= ev.sim.controllers.numpy()[0] == 2  # IDM: the five parked vehicles, not the pedestrian
    assert parked.sum() == 5
    xy0 = ev.sim.state.pos.numpy()[0][parked].copy()
    for _ in range(5):
        ev.sim.step(np.zeros((1, ev.sim.max_agents), np.int64))
    assert ev.sim.state.alive.numpy()[0][parked].all()
    assert (ev.sim.metrics["goal_step"][0].cpu().numpy()[parked] == -1).all()
    np.testing.assert_allclose(ev.sim.state.pos.numpy()[0][parked], xy0, atol=1e-3)  # IDM v0 = 0: parked


def test_ego_is_the_task_agent_not_the_sdc(tasks):
    """A task whose ego is another controllable agent: slot 0 is that agent, starts at its
    logged t0 pose and is scored against its own goal."""
    import dataclasses

    sc = tasks[0].scenario
    others = [int(i) for i in np.flatnonzero(sc.controllable) if i != sc.ego_index]
    assert others
    task = R.Task("random", 0, dataclasses.replace(sc, ego_index=others[0]))
    ev = R.Evaluator([task], ["replay"], config=R.EvalConfig(progress=False, record=(0,)))
    res = ev.run("expert")
    assert int(res.columns["ego"][0]) == others[0]
    traj = res.trajectories[0]
    np.testing.assert_allclose(traj["xy"][0, 0], sc.log_xy[others[0], 0], atol=1e-3)
    np.testing.assert_allclose(traj["goal_xy"], sc.goal_xy[others[0]], atol=1e-3)


def test_every_agent_is_tested_against_the_evaluation_goal(expert):
    """Co-players too: the evaluation goal test (2 m, no effective speed limit), whatever
    their condition. A co-player whose log passes its goal only faster than 5 m/s still
    arrives under replay."""
    from cpsim.config import EVAL_GOAL, Outcome

    ev, res = expert
    assert ev.sim.config.goal_criterion == "evaluation" and EVAL_GOAL.radius == 2.0 and EVAL_GOAL.speed >= 100
    fast_arrivals = 0
    for row, traj in res.trajectories.items():
        if res.columns["regime"][row] != "replay":
            continue
        sc = _scenario_of(ev, res.columns["scenario_id"][row])
        idx = ev.sim.model.slot_order[ev.scenario_index[(sc.id, sc.ego_index)]][:ev.sim.max_agents]
        for slot, agent in enumerate(idx[1:], start=1):
            d = np.linalg.norm(sc.log_xy[agent] - sc.goal_xy[agent], axis=-1)
            inside = sc.log_valid[agent] & (d < 2.0)
            inside[0] = False
            if inside.any() and (sc.log_speed[agent][inside] > 5.0).all():
                if int(traj["outcome"][slot]) in (int(Outcome.COLLISION), int(Outcome.OFFROAD)):
                    continue
                assert int(traj["outcome"][slot]) == int(Outcome.GOAL), (row, slot)
                fast_arrivals += 1
    assert fast_arrivals >= 1
