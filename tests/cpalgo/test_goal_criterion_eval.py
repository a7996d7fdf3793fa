"""One goal criterion in evaluation: selfplay_outcomes and the evaluator test every
deployment condition with the same goal (cpsim.config.EVAL_GOAL)."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium import spaces

pytest.importorskip("cpsim.simulator")

from cpalgo.anchor.outcomes import expert_outcomes, selfplay_outcomes  # noqa: E402
from cpalgo.evaluate import runner as R  # noqa: E402
from cpsim.conditions import STYLE_MASK, deployment_condition  # noqa: E402
from cpsim.scenario import generate  # noqa: E402
from tests.cpsim.scenes import LANE_WIDTH, agent, make_scenario  # noqa: E402

PROFILES = ("cautious", "normal", "aggressive")


class ConstantSpeed:
    """A stand-in SB3 model: zero jerks for every agent (keeps its speed, drives straight)."""

    def __init__(self, obs_size: int):
        self.observation_space = spaces.Box(-1.0, 1.0, (obs_size,), np.float32)
        self.seen: list[np.ndarray] = []

    def predict(self, obs, state=None, episode_start=None, deterministic=True):
        self.seen.append(obs.copy())
        return np.full(obs.shape[0], 2 * 3 + 1), state


def _fast_scenes():
    # two controllable cars at 10 m/s, goals 12 m ahead: they pass them at 10 m/s, faster than
    # the cautious profile's goal speed (5 m/s)
    return [make_scenario([agent(0.0, 0.0, speed=10.0, goal=(12.0, 0.0)),
                           agent(-30.0, LANE_WIDTH, speed=10.0, goal=(-18.0, LANE_WIDTH))], sid=f"fast{i}")
            for i in range(2)]


def test_selfplay_outcomes_use_one_goal_test_for_every_condition():
    import cpsim

    scenes = _fast_scenes()
    size = cpsim.Simulator(scenes, num_worlds=1, max_agents=2).obs_layout
    rates = {}
    for name in PROFILES:
        model = ConstantSpeed(size.size)
        rates[name] = selfplay_outcomes(model, scenes, condition=name, max_agents=2, config={"episode_steps": 20})
        # the policy sees the criterion's task fields, the same under every profile
        cond = model.seen[0][:, size.condition][:, ~STYLE_MASK]
        np.testing.assert_allclose(cond, np.broadcast_to(cond[0], cond.shape))
    for name in PROFILES:
        assert rates[name].goal == 1.0 and rates[name].agents == 4
        assert rates[name].as_dict() == rates["normal"].as_dict()


def test_expert_outcomes_do_not_depend_on_the_deployment_profile():
    scenes = [generate("intersection", 2**30 + s) for s in range(3)]
    out = {name: expert_outcomes(scenes, condition=name).as_dict() for name in PROFILES}
    assert out["cautious"] == out["normal"] == out["aggressive"]


def test_evaluator_tests_every_deployment_condition_with_the_evaluation_goal():
    tasks = [R.Task("random", i, sc) for i, sc in enumerate(_fast_scenes())]
    goals = {}
    for name in PROFILES:
        ev = R.Evaluator(tasks, ["replay", "static"], config=R.EvalConfig(deploy_condition=name, progress=False))
        assert ev.sim.config.goal_criterion == "evaluation"
        np.testing.assert_array_equal(ev.deploy, deployment_condition(name))
        res = ev.run(lambda obs: np.full(obs.shape[0], 2 * 3 + 1), label="constant")
        goals[name] = res.columns["goal"].copy()
    assert goals["cautious"].all()
    assert all(np.array_equal(goals[n], goals["normal"]) for n in PROFILES)
