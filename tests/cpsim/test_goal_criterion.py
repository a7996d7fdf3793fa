"""One goal criterion in evaluation: SimConfig.goal_criterion, EVAL_GOAL, deployment conditions."""

from __future__ import annotations

import numpy as np
import pytest

import cpsim
from cpsim.conditions import (
    FIELD_INDEX,
    PROFILES,
    STYLE_MASK,
    TRAIN_HIGH,
    TRAIN_LOW,
    deployment_condition,
    sample_conditions,
)
from cpsim.config import EVAL_GOAL, GOAL_CRITERIA, Outcome, SimConfig
from tests.cpsim.scenes import agent, make_scenario

KEEP_JERK = 2 * 3 + 1  # zero jerks: constant speed, straight


def test_the_criterion_is_named_in_the_config():
    assert EVAL_GOAL.name == "evaluation" and GOAL_CRITERIA["evaluation"] is EVAL_GOAL
    # BehaviorBench's evaluation goal test: 2 m, goal speed 100 m/s (no effective speed limit)
    assert (EVAL_GOAL.radius, EVAL_GOAL.speed) == (2.0, 100.0)
    assert SimConfig().goal_criterion == "condition"  # training: per-agent task fields
    assert SimConfig(goal_criterion="evaluation").to_dict()["goal_criterion"] == "evaluation"
    with pytest.raises(ValueError, match="goal_criterion"):
        SimConfig(goal_criterion="cautious")


def test_deployment_condition_changes_style_fields_only():
    task = ~STYLE_MASK
    conds = {name: deployment_condition(name) for name in PROFILES}
    first = next(iter(conds.values()))
    for name, c in conds.items():
        np.testing.assert_array_equal(c[STYLE_MASK], PROFILES[name][STYLE_MASK])  # the style
        np.testing.assert_array_equal(c[task], first[task])                        # one task
    # what the policy sees of the criterion: 2 m and the fastest goal speed it was trained on
    assert c[FIELD_INDEX["goal_radius"]] == 2.0
    assert c[FIELD_INDEX["goal_speed"]] == TRAIN_HIGH[FIELD_INDEX["goal_speed"]]
    raw = PROFILES["normal"].copy()
    raw[FIELD_INDEX["goal_speed"]] = 3.0
    np.testing.assert_array_equal(deployment_condition(raw), conds["normal"])
    assert raw[FIELD_INDEX["goal_speed"]] == 3.0  # the caller's vector is not modified
    with pytest.raises(ValueError, match="deploy"):
        deployment_condition("reckless", "deploy")


def _goal_steps(criterion: str, conds: np.ndarray, steps: int = 4) -> tuple[list[int], list[int]]:
    # ego at 10 m/s (1 m per step) heads to a goal 3.05 m ahead: within 2 m from step 2 on
    sc = make_scenario([agent(0.0, 0.0, speed=10.0, goal=(3.05, 0.0))])
    sim = cpsim.Simulator([sc], num_worlds=len(conds), max_agents=1, seed=0,
                          config=SimConfig(goal_criterion=criterion))
    sim.reset(conditions=conds[:, None])
    goal_steps = np.full(len(conds), -1)
    for t in range(1, steps + 1):
        sim.step(np.full((len(conds), 1), KEEP_JERK))
        goal_steps[sim.metrics["goal_step"][:, 0].numpy() == t] = t
    return goal_steps.tolist(), sim.outcome[:, 0].tolist()


def test_changing_the_profile_leaves_the_evaluation_goal_test_unchanged():
    # the full profiles, task fields included (cautious: goal speed 5 m/s), and extreme draws
    names = list(PROFILES)
    extreme = np.stack([TRAIN_LOW, TRAIN_HIGH])
    conds = np.concatenate([np.stack([PROFILES[n] for n in names]), extreme,
                            sample_conditions(np.random.default_rng(0), 3)])
    steps, outcome = _goal_steps("evaluation", conds)
    # radius 2 m and no speed limit for every world, whatever its condition
    assert steps == [2] * len(conds)
    assert outcome == [Outcome.GOAL] * len(conds)
    # the per-agent test (training) does depend on the task fields: cautious is too fast at
    # 10 m/s, and the 12 m radius of TRAIN_HIGH counts from the first step
    steps, _ = _goal_steps("condition", conds)
    by_name = dict(zip(names, steps))
    assert by_name["cautious"] == -1 and by_name["normal"] == 2 and by_name["aggressive"] == 2
    assert steps[len(names)] == -1 and steps[len(names) + 1] == 1
