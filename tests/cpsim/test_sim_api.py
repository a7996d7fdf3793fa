"""Simulator API: config validation, slot assignment, seeding, controllers, bad inputs
(ValueError naming the argument, state unchanged)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import cpsim
from cpsim.config import Controller, SimConfig
from cpsim.model import simplify_polyline
from tests.cpsim.scenes import LANE_WIDTH, agent, make_scenario, small_pool

NORMAL = cpsim.profile("normal")


def test_known_fields_names_the_config_and_every_unknown_key():
    """The check behind every settings dataclass's from_dict (ImitationConfig, DistillConfig,
    EvalConfig, bc.TrainConfig): the unknown keys and the accepted ones, before anything is built."""
    from cpalgo.traffic.bc import TrainConfig
    from cpsim.config import known_fields

    @dataclasses.dataclass(frozen=True)
    class Settings:
        lr: float = 1.0
        epochs: int = 2

    assert known_fields(Settings, {"lr": 0.5}, "Settings") == {"lr": 0.5}
    with pytest.raises(ValueError, match=r"Settings: unknown keys \['lrr', 'zeta'\]; accepted: \['epochs', 'lr'\]"):
        known_fields(Settings, {"lrr": 1, "zeta": 2, "epochs": 3}, "Settings")
    with pytest.raises(ValueError, match="Settings: expected a mapping, got list"):
        known_fields(Settings, [("lr", 1.0)], "Settings")
    with pytest.raises(ValueError, match=r"TrainConfig: unknown keys \['epoch'\]"):
        TrainConfig.from_dict({"epoch": 3})


def test_config_rejects_unknown_keys_and_bad_values():
    with pytest.raises(ValueError, match="unknown key.*'bogus'.*valid keys"):
        SimConfig.from_dict({"bogus": 1})
    for field, value in (("dynamics", "rocket"), ("on_goal", "explode"), ("dt", 0.0),
                         ("episode_steps", 0), ("episode_steps", 92), ("num_partners", -1),
                         ("box_scale", -1.0), ("default_controller", "none"), ("collide_types", "yes"),
                         ("partner_radius", float("nan"))):
        with pytest.raises(ValueError, match=f"SimConfig.{field}"):
            SimConfig.from_dict({field: value})
    cfg = SimConfig.from_dict({"dynamics": "classic", "num_partners": 63, "num_road": 200})
    assert cfg.num_actions == 91 and SimConfig().num_actions == 12
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.dt = 0.2  # frozen
    assert cfg.replace(box_scale=0.7).box_scale == 0.7


def test_slot_assignment_ego_controllable_then_others_and_truncation():
    sc = make_scenario([
        agent(50.0, 0.0, speed=5.0, goal=(100.0, 0.0)),                                # 0: controllable, 50 m from the ego
        agent(0.0, 0.0, speed=5.0, goal=(80.0, 0.0)),                                  # 1: ego
        agent(30.0, LANE_WIDTH, speed=5.0, goal=(90.0, LANE_WIDTH)),                   # 2: controllable, 30 m
        agent(5.0, LANE_WIDTH, speed=0.0),                                             # 3: parked, 6 m
        agent(-10.0, 0.0, speed=5.0, goal=(70.0, 0.0)),                                # 4: controllable, 10 m
        agent(2.0, 8.0, kind=cpsim.AgentType.PEDESTRIAN, speed=1.0, goal=(2.0, 30.0)),  # 5: pedestrian
        agent(1.0, 1.0, speed=5.0, goal=(80.0, 1.0), valid_steps=0),                   # 6: never valid
    ], ego=1)
    sim = cpsim.Simulator([sc], num_worlds=2, max_agents=6, seed=0)
    assert sim.agent_index[0].tolist() == [1, 4, 2, 0, 3, 5]
    assert sim.controllers[0].tolist() == [Controller.POLICY] * 4 + [Controller.REPLAY] * 2
    small = cpsim.Simulator([sc], num_worlds=1, max_agents=3, seed=0)
    assert small.agent_index[0].tolist() == [1, 4, 2]
    big = cpsim.Simulator([sc], num_worlds=1, max_agents=8, seed=0)
    assert big.agent_index[0].tolist()[6:] == [-1, -1]
    assert big.controllers[0, 6:].tolist() == [Controller.NONE, Controller.NONE]
    assert not big.alive[0, 6:].any() and np.all(big.obs[0, 6:].numpy() == 0)
    cfg = cpsim.Simulator([sc], num_worlds=1, max_agents=6, seed=0,
                          config={"default_controller": "idm", "other_controller": "static"})
    assert cfg.controllers[0].tolist() == [Controller.IDM] * 4 + [Controller.STATIC] * 2


def test_seeded_draws_are_reproducible():
    a = cpsim.Simulator(small_pool(3), num_worlds=6, max_agents=2, seed=7)
    b = cpsim.Simulator(small_pool(3), num_worlds=6, max_agents=2, seed=7)
    c = cpsim.Simulator(small_pool(3), num_worlds=6, max_agents=2, seed=8)
    assert torch.equal(a.conditions, b.conditions) and torch.equal(a.world_scenario, b.world_scenario)
    assert not torch.equal(a.conditions, c.conditions)
    assert ((a.conditions[..., 0] >= 2.0) & (a.conditions[..., 0] <= 12.0)).all()
    a.reset(worlds=[1, 4], scenario_index=2)
    assert a.world_scenario[[1, 4]].tolist() == [2, 2]
    assert a.step_count.tolist() == [0] * 6
    assert a.scenario_of(1).id == small_pool(3)[2].id


def test_actions_accept_torch_flat_and_integral_floats():
    sim = cpsim.Simulator(small_pool(1), num_worlds=2, max_agents=2, seed=0)
    sim.step(torch.full((2, 2), 7, dtype=torch.int64))
    sim.step(np.full(4, 7, np.int16))
    sim.step(np.full((2, 2), 7.0))
    assert sim.step_count.tolist() == [3, 3]


@pytest.fixture(scope="module")
def sim():
    s = cpsim.Simulator(small_pool(2), num_worlds=3, max_agents=2, seed=0)
    s.step(np.full((3, 2), 7))
    return s


BAD_CALLS = [
    ("actions", lambda s: s.step(np.zeros((3, 3), np.int64))),
    ("actions", lambda s: s.step(np.zeros((2, 2), np.int64))),
    ("actions", lambda s: s.step(np.full((3, 2), 12))),
    ("actions", lambda s: s.step(np.full((3, 2), -1))),
    ("actions", lambda s: s.step(np.full((3, 2), np.nan))),
    ("actions", lambda s: s.step(np.full((3, 2), 1.5))),
    ("actions", lambda s: s.step(np.full((3, 2), "a"))),
    ("actions", lambda s: s.step(torch.full((3, 2), 99))),
    ("conditions", lambda s: s.set_conditions(np.full(10, 100.0))),
    ("conditions", lambda s: s.set_conditions(np.zeros(9))),
    ("conditions", lambda s: s.reset(conditions=np.where(np.arange(10) == 1, 31.0, NORMAL))),
    ("worlds", lambda s: s.reset(worlds=[0, 3])),
    ("worlds", lambda s: s.reset(worlds=[-1])),
    ("worlds", lambda s: s.set_conditions(NORMAL, worlds=[5])),
    ("worlds", lambda s: s.reset(worlds=[1, 1])),
    ("scenario_index", lambda s: s.reset(scenario_index=2)),
    ("scenario_index", lambda s: s.reset(scenario_index=[0, 1])),
    ("controllers", lambda s: s.set_controllers(np.full((3, 2), 7))),
    ("controllers", lambda s: s.set_controllers(np.full((3, 2), Controller.NONE))),
    ("controllers", lambda s: s.set_controllers(np.zeros((3, 5), np.int32))),
    ("snapshot", lambda s: s.restore("not a snapshot", [0])),
]


@pytest.mark.parametrize("argument,call", BAD_CALLS)
def test_bad_input_raises_and_leaves_state_unchanged(sim, argument, call):
    before = sim.state_dict()
    rng_state = sim._rng.bit_generator.state
    with pytest.raises(ValueError, match=argument):
        call(sim)
    after = sim.state_dict()
    for k in before:
        assert np.array_equal(before[k], after[k]), k
    assert sim._rng.bit_generator.state == rng_state


def test_constructor_rejects_bad_arguments():
    pool = small_pool(1)
    for kwargs, arg in (({"num_worlds": 0}, "num_worlds"), ({"max_agents": 1.5}, "max_agents"),
                        ({"config": {"bogus": 1}}, "bogus"), ({"device": "tpu:9"}, "device"),
                        ({"seed": -1}, "seed: must be an integer >= 0")):
        full = {"num_worlds": 1, "max_agents": 2, **kwargs}
        with pytest.raises(ValueError, match=arg):
            cpsim.Simulator(pool, **full)
    with pytest.raises(ValueError, match="scenarios"):
        cpsim.Simulator([], num_worlds=1, max_agents=1)
    with pytest.raises(ValueError, match="scenarios"):
        cpsim.Simulator(["nope"], num_worlds=1, max_agents=1)


def test_outputs_are_zero_copy_views_and_shapes():
    sim = cpsim.Simulator(small_pool(2), num_worlds=3, max_agents=2, seed=0)
    D = sim.obs_layout.size
    assert sim.obs.shape == (3, 2, D) and sim.obs.dtype == torch.float32
    for name in ("reward", "speed", "heading", "accel", "steer"):
        assert getattr(sim, name).shape == (3, 2)
    for name in ("alive", "done", "terminated", "truncated"):
        assert getattr(sim, name).dtype == torch.bool
    assert sim.world_done.shape == (3,) and sim.step_count.dtype == torch.int32
    assert sim.xy.shape == (3, 2, 2) and sim.conditions.shape == (3, 2, 10)
    assert set(sim.metrics) == {"steps_alive", "comfort_violations", "aligned_steps", "lateral_offset_sum",
                                "first_collision_step", "collision_partner", "first_offroad_step",
                                "goal_step", "at_fault"}
    assert {k for k in sim.reward_terms if k.startswith("raw_")} == {f"raw_{t}" for t in cpsim.state.REWARD_TERMS}
    ptr = sim.obs.data_ptr()
    sim.step(np.full((3, 2), 7))
    assert sim.obs.data_ptr() == ptr  # overwritten in place by the next step
    assert torch.equal(sim.policy_mask, sim.alive & (sim.controllers == 0))


def test_simplify_polyline_keeps_shape():
    t = np.linspace(0, np.pi, 200)
    arc = np.stack([30 * np.cos(t), 30 * np.sin(t)], 1)
    keep = simplify_polyline(arc, 0.05, 10.0)
    assert keep[0] == 0 and keep[-1] == 199 and 10 < keep.size < 200
    seg = arc[keep]
    assert np.all(np.linalg.norm(np.diff(seg, axis=0), axis=1) <= 10.0 + 1e-9)
    # every original vertex lies within the tolerance of the simplified polyline
    from cpsim.model import point_segment_distance
    d = point_segment_distance(arc, seg[:-1], seg[1:]).min(1)
    assert d.max() <= 0.05 + 1e-9
    straight = np.stack([np.arange(0, 100.0, 0.5), np.zeros(200)], 1)
    assert simplify_polyline(straight, 0.05, 10.0).tolist() == list(range(0, 200, 20)) + [199]  # 10 m pieces
