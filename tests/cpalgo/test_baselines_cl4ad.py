"""CL4AD-dagger: the learnability curriculum over the training scenarios."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from cpalgo.baselines.cl4ad.curriculum import LearnabilitySampler  # noqa: E402
from cpalgo.methods.base import base_vec_env  # noqa: E402
from tests.cpalgo.test_baselines_common import anchor, build, collect  # noqa: E402,F401

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def test_sampler_prefers_scenarios_with_mixed_outcomes():
    s = LearnabilitySampler(4, temperature=0.5, uniform=0.2, decay=0.9, seed=0)
    s.update(np.zeros(20, int), np.ones(20, bool))              # 0: always completed
    s.update(np.ones(20, int), np.zeros(20, bool))              # 1: always failed
    s.update(np.full(20, 2), np.arange(20) % 2 == 0)            # 2: half and half
    # 3: never seen (estimated at 0.5: explored as if learnable)
    p = s.probabilities()
    assert p.sum() == pytest.approx(1.0)
    assert p[2] > 3 * p[0] and p[2] > 3 * p[1]
    assert p[3] >= p[2]
    assert np.all(p >= 0.2 / 4 - 1e-12)  # the uniform share keeps every scenario visited
    draws = np.bincount(s.sample(4000), minlength=4) / 4000
    assert draws[2] > 0.3 and draws[0] < 0.1 and draws[1] < 0.1
    # sharper temperature, no uniform share: almost only the learnable ones
    sharp = LearnabilitySampler(4, temperature=0.1, uniform=0.0)
    sharp.successes, sharp.episodes = s.successes.copy(), s.episodes.copy()
    assert sharp.probabilities()[[0, 1]].sum() < 0.01
    # the estimate follows the recent past: a settled scenario that starts failing becomes learnable
    assert s.learnability[0] < 0.1
    s.update(np.zeros(3, int), np.zeros(3, bool))
    assert s.learnability[0] > 0.15
    # uniform share 1: plain uniform sampling whatever the estimates
    flat = LearnabilitySampler(4, uniform=1.0)
    flat.successes, flat.episodes = s.successes.copy(), s.episodes.copy()
    assert flat.probabilities() == pytest.approx(np.full(4, 0.25))


def test_self_play_worlds_reset_into_the_curriculums_scenarios(anchor):
    model = build("cl4ad", anchor, curriculum_uniform=0.0, curriculum_temperature=0.05)
    env = base_vec_env(model.env)
    sampler = model.sampler
    assert sampler.num_scenarios == len(env.scenarios) == 4
    # scenario 2 is the only one with mixed outcomes; the others are settled
    sampler.successes[:] = [50.0, 0.0, 25.0, 50.0]
    sampler.episodes[:] = [50.0, 50.0, 50.0, 50.0]
    episodes_before = sampler.episodes.sum()
    collect(model)  # learn's env.reset and every auto-reset go through the curriculum
    curriculum = model._curriculum
    assert curriculum.resets.sum() >= env.num_worlds
    assert curriculum.resets[2] / curriculum.resets.sum() > 0.9
    ws = env.sim.world_scenario.cpu().numpy()
    assert np.sum(ws == 2) >= 1
    # the finished agent episodes updated the estimates of the scenarios they ran on
    assert model.curriculum_totals["agent_episodes"] > 0
    assert sampler.episodes.sum() != pytest.approx(episodes_before)
    # conditions are still drawn from p_train per agent (not one fixed condition)
    cond = env.sim.conditions.cpu().numpy().reshape(-1, 10)
    assert np.unique(cond[:, 0]).size > 1

