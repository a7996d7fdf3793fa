"""Data-parallel PPO (cpalgo.common.distributed, the all-reduce in cpalgo.common.ppo_update):
two gloo ranks against the single-process update on the same data."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch as th

from tests.cpalgo.fakes import SlotVecEnv

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py

#: one rollout of 16 steps x 4 slots (slot 3 never live, slot 2 in part): ~40 live transitions
SCENARIOS: dict[str, dict] = {
    # both ranks: the same seeds, so the same rollout; Adam, 3 minibatches x 2 epochs
    "same": dict(batch_size=16, n_epochs=2, sgd=False),
    # rank r samples its actions from torch seed 10 + r; plain SGD, one minibatch, one epoch:
    # the averaged step is the mean of the two single-process steps
    "different": dict(batch_size=64, n_epochs=1, sgd=True),
    # rank 1's rollout has no live transition: its minibatches are all padding (zero shares)
    "blank": dict(batch_size=16, n_epochs=2, sgd=False),
    # as "blank", with a scheduled loss term on 2 minibatch updates: rank 0 carries it in its
    # minibatches, rank 1 owes it (no minibatch of its own) and runs it after the loop
    "scheduled": dict(batch_size=16, n_epochs=2, sgd=False),
}


def _model(batch_size: int, n_epochs: int, sgd: bool):
    from cpalgo import CounterPlay

    policy_kwargs: dict = dict(lstm_hidden_size=8, net_arch=[8])
    if sgd:
        policy_kwargs.update(optimizer_class=th.optim.SGD, optimizer_kwargs={})
    # a huge max_grad_norm keeps the clip out of the SGD comparison (it is linear then)
    return CounterPlay("MlpLstmPolicy", SlotVecEnv(0), counterfactual=False, seed=1, n_steps=16,
                       batch_size=batch_size, n_epochs=n_epochs, device="cpu", learning_rate=0.05,
                       max_grad_norm=1e9 if sgd else 0.5, policy_kwargs=policy_kwargs)


def _params(model) -> dict[str, th.Tensor]:
    return {k: v.detach().clone() for k, v in model.policy.state_dict().items()}


def _one_update(scenario: str, rank: int) -> dict[str, th.Tensor]:
    """One rollout and one update of ``scenario`` as ``rank`` (with or without a group)."""
    model = _model(**SCENARIOS[scenario])
    th.manual_seed(10 + (rank if scenario == "different" else 0))
    if scenario == "blank" and rank == 1:
        train = model.train

        def blank_train() -> None:
            model.rollout_buffer.active[:] = 0  # every slot inactive: nothing for this rank to learn
            train()

        model.train = blank_train
    applied: list[int] = []
    if scenario == "scheduled":
        from cpalgo.common.ppo_update import ScheduledTerms, begin_update, run_update

        def scheduled_train() -> None:
            if rank == 1:
                model.rollout_buffer.active[:] = 0
            clip_range, clip_range_vf = begin_update(model)
            terms = ScheduledTerms(compute=lambda: {"l2": 1e-2 * sum((p ** 2).sum() for p in model.policy.parameters())},
                                   minibatches=2)
            run_update(model, clip_range, clip_range_vf, masked=True, scheduled=[terms])
            applied.append(len(terms.logs.get("l2", [])))

        model.train = scheduled_train
    model.learn(1)
    params = _params(model)
    if applied:
        params["applied"] = th.tensor(applied)
    return params


def _rank(rank: int, store: str, out: str) -> None:
    """A spawned rank: every scenario under one gloo group of 2, the parameters saved."""
    import torch.distributed as dist

    th.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=2)
    try:
        for scenario in SCENARIOS:
            params = _one_update(scenario, rank)
            th.save(params, os.path.join(out, f"{scenario}_{rank}.pt"))
    finally:
        dist.destroy_process_group()


@pytest.fixture(scope="module")
def ranks(tmp_path_factory) -> Path:
    """The parameters every rank ended with, per scenario (``{scenario}_{rank}.pt``)."""
    import torch.multiprocessing as mp

    out = tmp_path_factory.mktemp("ranks")
    mp.spawn(_rank, args=(str(out / "store"), str(out)), nprocs=2, join=True)
    return out


def _load(out: Path, scenario: str, rank: int) -> dict[str, th.Tensor]:
    return th.load(out / f"{scenario}_{rank}.pt", weights_only=True)


def _same(a: dict[str, th.Tensor], b: dict[str, th.Tensor]) -> bool:
    return a.keys() == b.keys() and all(th.equal(a[k], b[k]) for k in a)


def test_two_ranks_on_the_same_data_equal_one_process(ranks: Path):
    single = _one_update("same", 0)
    start = _params(_model(**SCENARIOS["same"]))
    assert not _same(single, start)  # the update moved the parameters
    assert _same(_load(ranks, "same", 0), single)
    assert _same(_load(ranks, "same", 1), single)


def test_two_ranks_average_their_gradients(ranks: Path):
    start = _params(_model(**SCENARIOS["different"]))
    a, b = _one_update("different", 0), _one_update("different", 1)
    assert not _same(a, b)  # the ranks' data differ
    got = _load(ranks, "different", 0)
    assert _same(got, _load(ranks, "different", 1))  # the ranks stay identical
    for k in got:
        # one SGD step on the mean gradient: the mean of the single-process steps (a sum
        # over ranks would double the step)
        np.testing.assert_allclose(got[k] - start[k], (a[k] - start[k] + b[k] - start[k]) / 2, rtol=1e-4,
                                   atol=1e-7)
    assert any(th.linalg.vector_norm(a[k] - start[k]) > 1e-4 for k in a)


def test_a_rank_without_live_data_adds_nothing_and_keeps_in_step(ranks: Path):
    # rank 1 had no minibatch at all: every step is rank 0's gradient alone (not halved), and
    # rank 1 took the same steps (same Adam moments), so both equal one process on rank 0's data
    single = _one_update("blank", 0)
    assert _same(_load(ranks, "blank", 0), single)
    assert _same(_load(ranks, "blank", 1), single)


def test_scheduled_terms_owed_by_one_rank_keep_the_ranks_in_step(ranks: Path):
    a, b = _load(ranks, "scheduled", 0), _load(ranks, "scheduled", 1)
    # rank 0 carried both scheduled updates in its minibatches, rank 1 ran both after its
    # (padding) minibatches; rank 0 added zero shares to those steps: same parameters
    assert a.pop("applied").tolist() == [2] and b.pop("applied").tolist() == [2]
    assert _same(a, b)
    assert not _same(a, _load(ranks, "blank", 0))  # the term's steps changed the update


def test_without_a_process_group_nothing_is_reduced():
    from cpalgo.common import distributed

    assert not distributed.data_parallel() and distributed.world_size() == 1 and distributed.rank() == 0
    assert distributed.agree_max(3) == 3 and distributed.joint_mean(None) != distributed.joint_mean(None)  # NaN
    np.testing.assert_array_equal(distributed.all_reduce_sum([1, 2]), [1.0, 2.0])
    assert distributed.gather_objects("x") == ["x"] and distributed.broadcast_object(5) == 5
