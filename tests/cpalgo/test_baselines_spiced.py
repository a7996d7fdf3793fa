"""SPICED-dagger: the KL penalty toward a frozen behaviour-cloning reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from cpalgo.methods.base import frozen_policy_copy  # noqa: E402
from cpalgo.traffic.bc import BCPolicy  # noqa: E402
from tests.cpalgo.fakes import minibatch_logits  # noqa: E402
from tests.cpalgo.test_baselines_common import anchor, build, collect  # noqa: E402,F401

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def minibatch_kls(model) -> list[float]:
    """Raw KL(reference || policy) of every minibatch of the collected rollout."""
    return [float(model._minibatch_terms(data, mask, logits)["spiced_kl_loss"]) / model.kl_coef
            for data, mask, logits in minibatch_logits(model)]


def test_kl_is_zero_when_the_policy_is_the_reference(anchor):
    model = build("spiced", anchor, kl_coef=1.0)
    model.reference_policy = frozen_policy_copy(model)  # recurrent reference, its own memory per slot
    collect(model)
    kls = minibatch_kls(model)
    assert kls and max(kls) < 1e-6
    # a reference that differs gives a positive KL on the same decisions
    other = build("spiced", anchor, kl_coef=1.0)
    th.manual_seed(5)
    for p in other.policy.parameters():
        p.data.add_(0.5 * th.randn_like(p))
    model.reference_policy = frozen_policy_copy(other)
    collect(model)
    assert min(minibatch_kls(model)) > 1e-3


def test_the_penalty_pulls_the_policy_toward_the_reference(anchor):
    model = build("spiced", anchor, kl_coef=2.0, learning_rate=3e-3, n_epochs=4, ent_coef=0.0)
    other = build("spiced", anchor)
    th.manual_seed(7)
    for p in other.policy.parameters():
        p.data.add_(0.3 * th.randn_like(p))
    model.reference_policy = frozen_policy_copy(other)
    collect(model)
    before = np.mean(minibatch_kls(model))
    model.train()
    after = np.mean(minibatch_kls(model))
    assert after < 0.8 * before
    # the logged KL is the raw KL over the update's minibatches: from "before" down toward "after"
    assert after <= model.logger.name_to_value["train/spiced_kl"] <= 1.01 * before


def test_tracking_reference_is_cloned_from_expert_labels_and_frozen(anchor):
    model = build("spiced", anchor)  # build_method calls on_anchor_loaded: the reference is trained
    ref = model.reference_policy
    assert isinstance(ref, BCPolicy)
    assert not any(p.requires_grad for p in ref.parameters())
    m = model.reference_metrics
    assert m["samples"] > 100 and 0.0 <= m["train_accuracy"] <= 1.0
    # the reference ignores the reward condition (a human reference knows none)
    layout = model.env.obs_layout
    obs = th.zeros(3, layout.size)
    shifted = obs.clone()
    shifted[:, layout.condition] = 0.7
    assert th.allclose(ref(obs), ref(shifted))
    # and it beats chance at predicting the expert on its own data (12 actions: 8.3 %)
    assert m["train_accuracy"] > 0.2


def test_shipped_reference_fits_and_a_bad_one_is_named(anchor, tmp_path):
    model = build("spiced", anchor, reference="shipped")
    assert isinstance(model.reference_policy, BCPolicy)
    assert model.reference_policy.obs_size == model.observation_space.shape[0]
    with pytest.raises(ValueError, match="^reference: no such"):
        build("spiced", anchor, reference=str(tmp_path / "missing.pt"))
    wrong = BCPolicy(10, 12)
    wrong.save(tmp_path / "wrong.pt")
    with pytest.raises(ValueError, match="^reference: .*observation size 10"):
        build("spiced", anchor, reference=str(tmp_path / "wrong.pt"))
