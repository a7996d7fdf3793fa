"""PlannerRFT-dagger: continuations against log-replayed traffic, a learned temperature, GRPO."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch as th

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from cpalgo.baselines.continuations import ContinuationRunner, GroupJob, branch_simulator_factory  # noqa: E402
from cpalgo.baselines.plannerrft.plannerrft import grpo_objective  # noqa: E402
from cpalgo.methods.base import base_vec_env  # noqa: E402
from cpsim.config import Controller  # noqa: E402
from tests.cpalgo.test_baselines_common import anchor, build, collect  # noqa: E402,F401

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def test_continuations_drive_against_log_replayed_traffic(anchor):
    model = build("plannerrft", anchor)
    collect(model)
    roots, results = model.last_groups
    assert roots
    for root, res in zip(roots, results):
        others = root.deciding.copy()
        others[root.focal] = False
        # co-players that were driving with the policy follow their logs in every continuation
        assert np.all(res.controllers[:, others] == int(Controller.REPLAY))
        assert np.all(res.controllers[:, root.focal] == int(Controller.POLICY))
    # positions: run one group on a fresh runner and compare with the scenario's logs
    sim = base_vec_env(model.env).sim
    root = next(r for r in roots if r.deciding.sum() >= 2)
    runner = ContinuationRunner(branch_simulator_factory(sim), model.policy, model.gamma, th.Generator().manual_seed(0))
    res = runner.run([GroupJob(root=root, traffic=["replay"] * 3)])[0]
    bsim = runner._sim
    scenario = bsim.scenario_of(0)
    index = bsim.agent_index.cpu().numpy()[0]
    checked = 0
    for a in np.flatnonzero(root.deciding):
        if a == root.focal:
            continue
        for k in range(1, int(res.length.min()) + 1):
            t = root.step + k
            if not scenario.log_valid[index[a], t]:
                break
            assert np.allclose(res.xy[:, k, a], scenario.log_xy[index[a], t], atol=1e-4)
            checked += 1
    assert checked > 0
    # closed-loop traffic (DAPO's) does not follow the logs
    closed = runner.run([GroupJob(root=root, traffic=["policy"] * 3)])[0]
    a = next(a for a in np.flatnonzero(root.deciding) if a != root.focal)
    k = int(closed.length.min())
    assert not np.allclose(closed.xy[:, k, a], scenario.log_xy[index[a], root.step + k], atol=1e-2)


def test_exploration_head_sets_bounded_temperatures_and_learns_from_group_returns(anchor):
    model = build("plannerrft", anchor, temperature_min=0.5, temperature_max=2.0, head_init_std=2.0, head_lr=0.05)
    collect(model)
    roots, _ = model.last_groups
    jobs = model._group_jobs(roots)
    temps = np.stack([j.temperature for j in jobs])
    assert temps.shape == (len(roots), model.group_size)
    assert np.all(temps >= 0.5 - 1e-6) and np.all(temps <= 2.0 + 1e-6) and temps.std() > 0
    # PPO on the head: continuations with higher temperature got higher returns -> the mean rises
    data = model._head_data
    x = data["x"]
    data["advantages"] = (x - x.mean(1, keepdim=True)) / (x.std(1, keepdim=True) + 1e-6)
    head = model.exploration_head
    obs = data["obs"]
    with th.no_grad():
        before = float(head(obs).mean.mean())
    model._train_head()
    with th.no_grad():
        after = float(head(obs).mean.mean())
    assert after > before
    assert model.continuation_totals["head_updates"] == model.head_epochs


def test_grpo_objective_is_a_per_continuation_mean():
    logp = th.zeros(2, 3)
    mask = th.tensor([[1.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    # equal ratios: each continuation counts once, however long (sample-level mean)
    value = float(grpo_objective(logp, th.zeros(2, 3), th.tensor([4.0, 0.0]), mask, 0.2))
    assert value == pytest.approx(2.0)
    # symmetric clip
    big = th.full((1, 1), math.log(1.5))
    assert float(grpo_objective(big, th.zeros(1, 1), th.tensor([1.0]), th.ones(1, 1), 0.2)) == pytest.approx(1.2)


def test_plannerrft_generation_updates_the_policy_with_the_group_term(anchor):
    model = build("plannerrft", anchor)
    collect(model)
    assert model._has_generation_terms()
    model.train()
    assert "train/grpo_loss" in model.logger.name_to_value
    assert "train/exploration_head_loss" in model.logger.name_to_value
