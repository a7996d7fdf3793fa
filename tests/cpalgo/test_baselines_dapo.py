"""DAPO-dagger: dynamic sampling drops all-success / all-fail groups; decoupled clipping."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch as th

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from cpalgo.baselines.dapo.dapo import decoupled_clip_objective, dynamic_sampling_keep  # noqa: E402
from tests.cpalgo.test_baselines_common import anchor, build, collect  # noqa: E402,F401

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def test_dynamic_sampling_keeps_only_groups_with_mixed_outcomes():
    completed = np.array([[1, 1, 1, 1, 1, 1], [0, 0, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0], [0, 1, 1, 1, 1, 1]], bool)
    assert dynamic_sampling_keep(completed).tolist() == [False, False, True, True]


def test_decoupled_clip_lets_unlikely_actions_rise_further_than_they_may_fall():
    mask = th.ones(1, 1)
    old = th.zeros(1, 1)

    def objective(ratio: float, adv: float, low: float = 0.2, high: float = 0.28) -> float:
        logp = th.full((1, 1), math.log(ratio))
        return float(decoupled_clip_objective(logp, old, th.tensor([adv]), mask, low, high))

    assert objective(1.25, 1.0) == pytest.approx(1.25)            # inside (1 - 0.2, 1 + 0.28): not clipped
    assert objective(1.25, 1.0, high=0.2) == pytest.approx(1.2)   # PPO's symmetric clip would cut it
    assert objective(1.40, 1.0) == pytest.approx(1.28)
    assert objective(0.70, -1.0) == pytest.approx(-0.8)           # the lower bound stays 1 - 0.2
    # token-level mean: every decision weighs the same, whatever its continuation's length
    logp = th.zeros(2, 3)
    m = th.tensor([[1.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    value = float(decoupled_clip_objective(logp, th.zeros(2, 3), th.tensor([4.0, 0.0]), m, 0.2, 0.28))
    assert value == pytest.approx(4.0 / 4)


def test_groups_whose_continuations_all_complete_or_all_fail_are_dropped(anchor):
    model = build("dapo", anchor)
    collect(model)
    roots, results = model.last_groups
    assert len(roots) >= 3
    g = model.group_size
    patterns = [np.ones(g, bool), np.zeros(g, bool), np.arange(g) < 2] + [np.arange(g) < 3] * (len(roots) - 3)
    faked = [dataclasses.replace(res, completed=p, returns=p.astype(float) + 0.1 * np.arange(g))
             for res, p in zip(results, patterns)]
    before = dict(model.continuation_totals)
    model._use_groups(roots, faked)
    batch = model._group_batch
    kept = len(roots) - 2
    assert batch.size == kept * g
    assert sorted(set(batch.group.tolist())) == list(range(kept))
    assert model.continuation_totals["groups_dropped"] - before.get("groups_dropped", 0) == 2
    assert model.continuation_totals["groups_kept"] - before.get("groups_kept", 0) == kept
    # the kept groups' advantages are group-relative: zero mean within each group
    for k in range(kept):
        assert float(batch.advantages[batch.group == k].mean()) == pytest.approx(0.0, abs=1e-5)
    # the dropped groups' transitions were spent all the same
    assert model.budget.candidate == sum(int(r.transitions.sum()) for r in results)
    # the group term trains the policy through the decoupled clip
    terms = model._generation_terms(0.2)
    model.policy.optimizer.zero_grad()
    terms["dapo_group_loss"].backward()
    assert any(p.grad is not None and float(p.grad.abs().sum()) > 0 for p in model.policy.parameters())
    assert model._clip_bounds(0.2) == (0.2, 0.28)  # the main PPO update clips the same way


def test_nothing_to_learn_when_every_group_is_settled(anchor):
    model = build("dapo", anchor)
    collect(model)
    roots, results = model.last_groups
    model._use_groups(roots, [dataclasses.replace(r, completed=np.zeros_like(r.completed)) for r in results])
    assert model._group_batch is None and not model._has_generation_terms()
    model.train()  # a plain PPO update then
    assert "train/dapo_group_loss" not in model.logger.name_to_value
