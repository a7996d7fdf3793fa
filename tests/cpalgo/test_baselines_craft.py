"""CRAFT-dagger: the hold-then-decay traffic proxy, the closed-loop residual, the EMA KL."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from cpalgo.baselines.continuations import action_grid  # noqa: E402
from cpalgo.baselines.craft.craft import ResidualTable, score_function_objective  # noqa: E402
from cpalgo.baselines.craft.proxy import hold_then_decay  # noqa: E402
from tests.cpalgo.test_baselines_common import anchor, build, collect  # noqa: E402,F401

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def components(actions, dynamics="jerk"):
    first, second = action_grid(dynamics)
    a = np.asarray(actions)
    return first[a // second.size], second[a % second.size]


def test_proxy_holds_the_last_action_then_decays_it_to_neutral():
    last = np.arange(12)  # every jerk action
    for k in range(3):
        assert np.array_equal(hold_then_decay(last, k, hold=3, decay=0.5), last)
    prev = components(last)
    for k in range(3, 12):
        act = hold_then_decay(last, k, hold=3, decay=0.5)
        cur = components(act)
        assert np.all(np.abs(cur[0]) <= np.abs(prev[0])) and np.all(np.abs(cur[1]) <= np.abs(prev[1]))
        assert np.all(np.sign(cur[0]) * np.sign(components(last)[0]) >= 0)  # never flips direction
        prev = cur
    assert np.all(hold_then_decay(last, 11, hold=3, decay=0.5) == 7)  # (0, 0) jerk
    # the strongest braking decays to the nearest levels: -15 x 0.5 = -7.5 -> -4, x 0.25 -> -4, x 0.125 -> 0
    brake = np.array([1])  # (-15, 0)
    seq = [float(components(hold_then_decay(brake, k, hold=0, decay=0.5))[0][0]) for k in range(4)]
    assert seq == [-4.0, -4.0, 0.0, 0.0]
    # the classic action set decays accelerations and steering the same way
    c = hold_then_decay(np.array([90]), 40, hold=0, decay=0.8, dynamics="classic")
    assert c.tolist() == [45]
    with pytest.raises(ValueError, match="last_actions"):
        hold_then_decay(np.array([12]), 0, hold=1, decay=0.5)


def test_proxy_continuations_use_the_proxy_and_pair_with_closed_loop_ones(anchor):
    model = build("craft", anchor, proxy_hold=2, proxy_decay=0.5)
    collect(model)
    roots, results = model.last_groups
    assert roots
    r = model.residual_rollouts
    for root, res in zip(roots, results):
        others = np.flatnonzero(root.deciding)
        others = others[others != root.focal]
        for j in range(r, model.group_size):  # proxy continuations
            for k in range(int(res.length[j])):
                acted = res.coplayer_actions[j, k, others]
                live = acted >= 0
                expected = hold_then_decay(root.last_actions[others], k, 2, 0.5)
                assert np.array_equal(acted[live], expected[live])
        # closed-loop continuation 0 and proxy continuation r share the focal draws: same
        # state, memory and uniform at the root -> the same first action
        assert res.actions[0, 0] == res.actions[r, 0]


def test_residual_table_corrects_proxy_returns_by_outcome():
    table = ResidualTable(decay=0.5)
    assert np.allclose(table.correct([1.0, 2.0], [1, 2]), [1.0, 2.0])  # nothing seen: no correction
    table.update(2, -3.0)  # collisions under the proxy: closed loop did 3 worse
    table.update(2, -1.0)
    assert table.value[2] == pytest.approx(-2.0) and table.count[2] == 2
    assert np.allclose(table.correct([1.0, 1.0], [1, 2]), [1.0, -1.0])


def test_craft_objective_and_ema(anchor):
    model = build("craft", anchor, ema_decay=0.5)
    assert model.ema_policy is not None  # started at the anchor by the registry
    collect(model)
    batch = model._group_batch
    assert batch is not None and model._ema_logits is not None
    # the corrected returns were used: proxy continuations shifted by the residual table
    _, results = model.last_groups
    assert model.residual.count.sum() == len(results) * model.residual_rollouts
    terms = model._generation_terms(0.2)
    assert set(terms) == {"craft_score_loss", "craft_kl_forward", "craft_kl_reverse"}
    # the policy equals its EMA right after the anchor: both KL terms are zero
    assert float(terms["craft_kl_forward"].detach()) == pytest.approx(0.0, abs=1e-7)
    assert float(terms["craft_kl_reverse"].detach()) == pytest.approx(0.0, abs=1e-7)
    old_ema = {k: v.clone() for k, v in model.ema_policy.state_dict().items()}
    model.train()
    new = model.policy.state_dict()
    for name, value in model.ema_policy.state_dict().items():
        if value.dtype.is_floating_point:
            assert th.allclose(value, 0.5 * old_ema[name] + 0.5 * new[name], atol=1e-6)


def test_score_function_objective_weights_each_candidate_by_its_advantage():
    logp = th.tensor([[-1.0, -1.0], [-2.0, 0.0]])
    mask = th.tensor([[1.0, 1.0], [1.0, 0.0]])
    adv = th.tensor([1.0, -1.0])
    # candidate 0: +1 x mean(-1, -1); candidate 1: -1 x (-2)
    assert float(score_function_objective(logp, adv, mask)) == pytest.approx((-1.0 + 2.0) / 2)
