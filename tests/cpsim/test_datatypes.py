"""Scenario validation and reward-condition helpers."""

from __future__ import annotations

import numpy as np
import pytest

import cpsim
from cpsim.conditions import (
    CONDITION_FIELDS,
    PANEL,
    PROFILES,
    STYLE_MASK,
    TRAIN_HIGH,
    TRAIN_LOW,
    criterion_task_fields,
    normalize_condition,
    resolve_condition,
    sample_conditions,
    validate_conditions,
    with_eval_task,
    with_panel_share,
    with_panel_styles,
)
from cpsim.scenario import AgentType, RoadType, Scenario, ScenarioError


def make_fields(n: int = 3) -> dict:
    t = 91
    xy = np.zeros((n, t, 2), np.float32)
    xy[:, :, 0] = np.linspace(0, 30, t)[None] + 10 * np.arange(n)[:, None]
    return dict(
        id="hand-0",
        log_xy=xy,
        log_heading=np.zeros((n, t), np.float32),
        log_velocity=np.tile(np.array([3.0, 0.0], np.float32), (n, t, 1)),
        log_valid=np.ones((n, t), bool),
        goal_xy=xy[:, -1].copy(),
        sizes=np.tile(np.array([4.5, 2.0], np.float32), (n, 1)),
        agent_types=np.zeros(n, np.int8),
        road_points=np.array([[0, 0], [100, 0], [0, 4], [100, 4]], np.float32),
        road_offsets=np.array([0, 2, 4], np.int32),
        road_types=np.array([RoadType.LANE, RoadType.ROAD_EDGE], np.int8),
        ego_index=0,
    )


def test_valid_scenario_derived_fields():
    s = Scenario(**make_fields())
    assert s.num_agents == 3 and s.num_roads == 2 and s.num_steps == 91
    assert s.log_xy.dtype == np.float32 and s.road_offsets.dtype == np.int32
    np.testing.assert_allclose(s.log_speed, 3.0)
    assert s.controllable.tolist() == [True, True, True]
    np.testing.assert_array_equal(s.road(1), [[0, 4], [100, 4]])
    assert not s.log_xy.flags.writeable  # scenarios are immutable data
    assert s == Scenario(**make_fields())


def test_controllable_excludes_pedestrians_invalid_and_short_goals():
    f = make_fields(4)
    f["agent_types"][1] = AgentType.PEDESTRIAN
    f["log_valid"][2, 0] = False
    f["goal_xy"][3] = f["log_xy"][3, 0] + 1.0  # 1.4 m < 2 m
    s = Scenario(**f)
    assert s.controllable.tolist() == [True, False, False, False]


def test_invalid_steps_may_hold_sentinel_coordinates():
    f = make_fields()
    f["log_valid"][1, 50:] = False
    f["log_xy"][1, 50:] = -10000.0
    f["log_heading"][1, 50:] = np.nan
    Scenario(**f)  # no error: invalid steps are never read


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda f: f.update(log_xy=f["log_xy"][:, :90]), "log_xy"),
        (lambda f: f["log_heading"].__setitem__((0, 3), np.nan), "log_heading"),
        (lambda f: f["log_velocity"].__setitem__((0, 3, 0), np.inf), "log_velocity"),
        (lambda f: f["sizes"].__setitem__((1, 0), -1.0), "sizes"),
        (lambda f: f.update(road_offsets=np.array([0], np.int32), road_types=np.zeros(0, np.int8)), "roads"),
        (lambda f: f.update(log_valid=np.zeros((3, 91), bool)), "valid"),
        (lambda f: f.update(ego_index=7), "ego_index"),
        (lambda f: f.update(goal_xy=np.zeros((2, 2), np.float32)), "goal_xy"),
        (lambda f: f.update(road_offsets=np.array([0, 1, 5], np.int32)), "road_offsets"),
    ],
)
def test_bad_scenarios_raise_with_field(mutate, field):
    f = make_fields()
    f["source"] = "file.json"
    mutate(f)
    with pytest.raises(ScenarioError) as err:
        Scenario(**f)
    assert isinstance(err.value, ValueError)
    assert "file.json" in str(err.value) and f"'{field}'" in str(err.value)


def test_validate_scenarios_is_the_one_list_check():
    from cpsim.envs.selfplay import resolve_scenarios
    from cpsim.scenario import interactive_split
    from cpsim.scenario.datatypes import validate_scenarios

    sc = Scenario(**make_fields())
    assert validate_scenarios(sc) == [sc] and validate_scenarios((sc, sc)) == [sc, sc]
    assert validate_scenarios([], needs=None) == []
    with pytest.raises(ValueError, match="scenarios: empty; a pool needs at least one scenario"):
        validate_scenarios([], needs="a pool")
    with pytest.raises(ValueError, match=r"tasks\[1\]: expected a Scenario \(cpsim.Scenario\), got str"):
        validate_scenarios([sc, "x"], "tasks")
    # the same messages from every API that takes scenarios
    for call in (lambda x: cpsim.Simulator(x, num_worlds=1, max_agents=1), resolve_scenarios,
                 lambda x: interactive_split(x, 1)):
        with pytest.raises(ValueError, match="scenarios: empty; .* needs at least one scenario"):
            call([])
        with pytest.raises(ValueError, match=r"scenarios\[0\]: expected a Scenario"):
            call([1])


def test_profiles_and_midpoints():
    assert set(PANEL) <= set(PROFILES)
    np.testing.assert_allclose(
        PROFILES["normal-aggressive"], 0.5 * (PROFILES["normal"] + PROFILES["aggressive"])
    )
    assert PROFILES["cautious"][CONDITION_FIELDS.index("goal_speed")] == 5.0
    assert cpsim.profile("halfway").tolist() == PROFILES["normal-aggressive"].tolist()
    with pytest.raises(ValueError, match="unknown profile"):
        cpsim.profile("reckless")
    # retries may change style fields only, never the goal test
    assert not STYLE_MASK[CONDITION_FIELDS.index("goal_radius")]
    assert STYLE_MASK[CONDITION_FIELDS.index("collision")]


def test_condition_sampling_and_normalisation():
    c = sample_conditions(np.random.default_rng(0), (50, 4))
    assert c.shape == (50, 4, 10) and c.dtype == np.float32
    assert np.all(c >= TRAIN_LOW) and np.all(c <= TRAIN_HIGH)
    n = normalize_condition(c)
    assert np.all(n >= -1.0) and np.all(n <= 1.0)
    np.testing.assert_allclose(normalize_condition(TRAIN_LOW), -1.0)
    np.testing.assert_allclose(normalize_condition(TRAIN_HIGH), 1.0)
    validate_conditions(c)


def test_condition_validation_names_field():
    bad = PROFILES["normal"].copy()
    bad[CONDITION_FIELDS.index("collision")] = 5.0
    with pytest.raises(ValueError, match="collision"):
        validate_conditions(bad, "deploy_condition")
    with pytest.raises(ValueError, match="deploy"):
        resolve_condition([1.0, 2.0], "deploy")
    np.testing.assert_array_equal(resolve_condition("normal"), PROFILES["normal"])


def test_normalize_condition_keeps_a_tensors_dtype():
    torch = pytest.importorskip("torch")
    c = sample_conditions(np.random.default_rng(1), 3)
    for dtype in (torch.float16, torch.float64):
        n = normalize_condition(torch.as_tensor(c, dtype=dtype))
        assert isinstance(n, torch.Tensor) and n.dtype == dtype
        np.testing.assert_allclose(n.double().numpy(), normalize_condition(c), atol=2e-3)


def test_with_panel_styles_indexes_the_panel_in_order():
    base = sample_conditions(np.random.default_rng(2), (2, len(PANEL)))
    index = np.array([np.arange(len(PANEL)), np.arange(len(PANEL))[::-1]])
    out = with_panel_styles(base, index)
    assert out.shape == base.shape and out.dtype == np.float32
    for i in range(2):
        for j in range(len(PANEL)):
            want = PROFILES[PANEL[index[i, j]]]
            np.testing.assert_array_equal(out[i, j, STYLE_MASK], want[STYLE_MASK])  # PANEL[index]'s style
            np.testing.assert_array_equal(out[i, j, ~STYLE_MASK], base[i, j, ~STYLE_MASK])  # own task


def test_with_panel_share_draws_index_then_pick():
    base = sample_conditions(np.random.default_rng(3), (40, 3))
    before = base.copy()
    out = with_panel_share(np.random.default_rng(7), base, 0.5)
    np.testing.assert_array_equal(base, before)  # the input is not modified
    # the documented draws, in order: a profile index per agent, then whether it takes it
    rng = np.random.default_rng(7)
    index = rng.integers(0, len(PANEL), size=(40, 3))
    pick = rng.random((40, 3)) < 0.5
    assert 0 < pick.mean() < 1
    np.testing.assert_array_equal(out[pick], with_panel_styles(base, index)[pick])
    np.testing.assert_array_equal(out[~pick], base[~pick])


def test_with_eval_task_sets_task_fields_in_place():
    base = sample_conditions(np.random.default_rng(4), (50, 2))
    before = base.copy()
    out = with_eval_task(np.random.default_rng(9), base, 0.5)
    assert out is base  # in place: callers may ignore the return value
    pick = np.random.default_rng(9).random((50, 2)) < 0.5
    assert 0 < pick.mean() < 1
    np.testing.assert_array_equal(base[pick][:, ~STYLE_MASK], np.broadcast_to(criterion_task_fields(), (pick.sum(), 2)))
    np.testing.assert_array_equal(base[~pick], before[~pick])
    np.testing.assert_array_equal(base[..., STYLE_MASK], before[..., STYLE_MASK])  # styles untouched
