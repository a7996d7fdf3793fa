"""Hand-made checks of the shared PPO update's advantage normalisation."""

from __future__ import annotations

import torch as th

from cpalgo.common.ppo_update import normalize_advantages


def test_normalize_advantages_uses_masked_moments_like_sb3_contrib():
    adv = th.tensor([1.0, 2.0, 3.0, 100.0])
    mask = th.tensor([True, True, True, False])
    got = normalize_advantages(adv, mask)
    live = adv[:3]
    expected = (adv - live.mean()) / (live.std() + 1e-8)
    assert th.allclose(got, expected)
    assert th.allclose(got[:3], th.tensor([-1.0, 0.0, 1.0]), atol=1e-6)


def test_normalize_advantages_keeps_a_single_live_transition_finite():
    adv = th.tensor([0.5, -2.0, 7.0])
    one = th.tensor([False, True, False])
    assert th.equal(normalize_advantages(adv, one), adv)  # std of one value is NaN
    assert th.equal(normalize_advantages(adv, th.zeros(3, dtype=th.bool)), adv)
