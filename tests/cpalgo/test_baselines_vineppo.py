"""VinePPO-dagger: the critic's value at a root is replaced by the continuation mean."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from tests.cpalgo.test_baselines_common import anchor, build, collect  # noqa: E402,F401

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def test_root_value_is_the_mean_continuation_return_and_enters_the_advantages(anchor):
    model = build("vineppo", anchor)
    buf = model.rollout_buffer
    captured = {}
    original = buf.compute_returns_and_advantage

    def capture(last_values, dones):
        captured.update(last_values=last_values.clone(), dones=np.array(dones, copy=True))
        original(last_values, dones)

    buf.compute_returns_and_advantage = capture
    collect(model)
    roots, results = model.last_groups
    assert roots and len(model.vine_values) == len(roots)
    for root, res, row in zip(roots, results, model.vine_values):
        mc = float(np.mean(res.returns))
        assert float(buf.values[root.buffer_pos, root.env_index]) == pytest.approx(mc, rel=1e-5, abs=1e-6)
        assert row["mc_value"] == pytest.approx(mc) and row["critic_value"] != pytest.approx(mc)
    # GAE used the Monte Carlo values: redoing it with the critic's values moves each
    # root's advantage by exactly (critic - MC) (A_t = r_t + gamma V_t+1 - V_t + ...)
    adv_mc = buf.advantages.copy()
    returns_mc = buf.returns.copy()
    for row in model.vine_values:
        buf.values[row["buffer_pos"], row["env_index"]] = row["critic_value"]
    buf.before_gae = None
    original(captured["last_values"], captured["dones"])
    for row in model.vine_values:
        p, e = row["buffer_pos"], row["env_index"]
        later = [r for r in model.vine_values if r["env_index"] == e and r["buffer_pos"] > p]
        if later:  # a later root of the same slot also changed this advantage
            continue
        assert adv_mc[p, e] - buf.advantages[p, e] == pytest.approx(row["critic_value"] - row["mc_value"], abs=1e-4)
        # the value target at the root is advantage + MC value
        assert returns_mc[p, e] == pytest.approx(adv_mc[p, e] + row["mc_value"], abs=1e-4)


def test_vineppo_trains_no_group_objective(anchor):
    model = build("vineppo", anchor)
    collect(model)
    assert model.last_groups[0] and model._group_batch is None
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.train()
    assert any(not th.equal(a, b) for a, b in zip(before, model.policy.parameters()))
    assert not any(k.startswith(("train/dapo", "train/grpo")) for k in model.logger.name_to_value)
