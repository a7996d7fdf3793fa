"""Snapshots: bit-exact round trips on CPU, a second Simulator, one-to-many broadcast,
every State field copied and no StepScratch field (scratch is rewritten by every step before
it is read), incompatible snapshots rejected; the CUDA variant when a GPU exists."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import warp as wp

import cpsim
from cpsim.config import Controller
from cpsim.kernels.snapshot import copy_worlds_kernel
from cpsim.state import scratch_field_names, state_field_names
from tests.cpsim.scenes import LANE_WIDTH, agent, make_scenario, small_pool

W, A = 4, 4


def pool():
    extra = make_scenario([agent(0.0, 0.0, speed=12.0, goal=(90.0, 0.0)),
                           agent(12.0, 0.0, speed=6.0, goal=(90.0, 0.0)),
                           agent(-10.0, LANE_WIDTH, speed=9.0, goal=(90.0, LANE_WIDTH)),
                           agent(30.0, LANE_WIDTH, speed=2.0, valid_steps=40)], sid="busy")
    return small_pool(2) + [extra]


def make_sim(seed=0, device="cpu", **cfg):
    sim = cpsim.Simulator(pool(), num_worlds=W, max_agents=A, seed=seed, device=device, config=cfg or None)
    sim.reset(scenario_index=[2, 2, 0, 1])
    # a mixture of controllers so replay, IDM and policy state all matter
    sim.set_controllers(np.array([Controller.POLICY, Controller.IDM, Controller.POLICY, Controller.REPLAY]), worlds=[0, 1])
    return sim


def run(sim, actions):
    for a in actions:
        sim.step(a)


def assert_same(d1, d2, rows1=slice(None), rows2=slice(None), exact=True):
    assert d1.keys() == d2.keys()
    for k in d1:
        a, b = d1[k][rows1], d2[k][rows2]
        if exact:
            assert np.array_equal(a, b), k
        else:
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4, err_msg=k)


def test_copy_kernel_copies_every_state_field():
    src = inspect.getsource(copy_worlds_kernel.func)
    for name in state_field_names():
        assert f"dst.{name}[d" in src, f"copy_worlds_kernel misses State.{name}"
    for name in scratch_field_names():
        assert name not in state_field_names() and f".{name}[" not in src, f"copy_worlds_kernel copies scratch {name}"


def scribble(arrays, names, rows):
    """Overwrite ``rows`` of every named field (CPU arrays are NumPy views)."""
    for name in names:
        arr = getattr(arrays, name).numpy()
        if arr.dtype == np.bool_:
            arr[rows] = ~arr[rows]
        else:
            arr[rows] = (arr[rows] + 7).astype(arr.dtype)


def test_round_trip_is_bit_exact_and_restore_overwrites_every_field():
    sim = make_sim()
    rng = np.random.default_rng(0)
    run(sim, rng.integers(0, 12, size=(6, W, A)))
    snap = sim.snapshot(np.arange(W))
    at_snapshot = sim.state_dict()
    future = rng.integers(0, 12, size=(15, W, A))
    run(sim, future)
    reference = sim.state_dict()
    # scribble over every field of world 2 before restoring, and over the per-step scratch
    # of every world (not restored: the next step rewrites it before reading it)
    scribble(sim.state, state_field_names(), 2)
    scribble(sim.scratch, scratch_field_names(), slice(None))
    sim.restore(snap, np.arange(W))
    assert_same(at_snapshot, sim.state_dict())
    assert not set(scratch_field_names()) & set(sim.state_dict())
    run(sim, future)
    assert_same(reference, sim.state_dict())


def test_restore_into_second_simulator_and_one_to_many():
    sim = make_sim(seed=0)
    other = make_sim(seed=123)  # same pool and config, different RNG and worlds
    rng = np.random.default_rng(1)
    run(sim, rng.integers(0, 12, size=(5, W, A)))
    root = sim.snapshot([0])
    root_state = sim.state_dict()
    # one root into three branch worlds of the other simulator
    other.restore(root, [3, 1, 2], source=[0, 0, 0])
    d = other.state_dict()
    for w in (1, 2, 3):
        assert_same(root_state, d, rows1=0, rows2=w)
    # the same actions in every branch give identical branches, equal to the original world
    acts = rng.integers(0, 12, size=(10, A))
    for a in acts:
        sim.step(np.broadcast_to(a, (W, A)))
        other.step(np.broadcast_to(a, (W, A)))
    d1, d2 = sim.state_dict(), other.state_dict()
    for w in (1, 2, 3):
        assert_same(d1, d2, rows1=0, rows2=w)


def test_snapshot_reuses_storage_and_rejects_incompatible():
    sim = make_sim()
    snap = sim.snapshot([1, 2])
    again = sim.snapshot([3, 0], out=snap)
    assert again is snap and snap.worlds.tolist() == [3, 0]
    before = sim.state_dict()
    different_pool = cpsim.Simulator(small_pool(3), num_worlds=W, max_agents=A, seed=0)
    with pytest.raises(ValueError, match="different scenario pool"):
        different_pool.restore(snap, [0, 1])
    different_cfg = cpsim.Simulator(pool(), num_worlds=W, max_agents=A, seed=0, config={"box_scale": 0.7})
    with pytest.raises(ValueError, match="SimConfig"):
        different_cfg.restore(snap, [0, 1])
    fewer_slots = cpsim.Simulator(pool(), num_worlds=W, max_agents=A - 1, seed=0)
    with pytest.raises(ValueError, match="max_agents"):
        fewer_slots.restore(snap, [0, 1])
    with pytest.raises(ValueError, match="source"):
        sim.restore(snap, [0, 1], source=[0, 2])
    with pytest.raises(ValueError, match="worlds"):
        sim.restore(snap, [0, 1, 2])
    with pytest.raises(ValueError, match="duplicate"):
        sim.restore(snap, [1, 1], source=[0, 0])
    with pytest.raises(ValueError, match="out of range"):
        sim.snapshot([0, W])
    assert_same(before, sim.state_dict())


def test_snapshot_state_dict_matches_world_rows():
    sim = make_sim()
    run(sim, np.full((3, W, A), 7))
    snap = sim.snapshot([2, 0])
    sd, full = snap.state_dict(), sim.state_dict()
    for name in state_field_names():
        np.testing.assert_array_equal(sd[name], full[name][[2, 0]])


@pytest.mark.cuda
@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device")
def test_round_trip_on_cuda_matches_cpu_up_to_float_tolerance():
    cpu, gpu = make_sim(device="cpu"), make_sim(device="cuda:0")
    rng = np.random.default_rng(2)
    acts = rng.integers(0, 12, size=(8, W, A))
    run(cpu, acts[:4])
    run(gpu, acts[:4])
    snap = gpu.snapshot(np.arange(W))
    run(gpu, acts[4:])
    ref = gpu.state_dict()
    gpu.restore(snap, np.arange(W))
    run(gpu, acts[4:])
    # on CUDA a restore + replay reproduces the run (same kernels, same order per thread)
    assert_same(ref, gpu.state_dict(), exact=False)
    run(cpu, acts[4:])
    assert_same(cpu.state_dict(), gpu.state_dict(), exact=False)
