"""RootStore: ring of roots, traces and search requests (no simulator needed)."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th

from cpalgo.counterplay.roots import RootStore


def _store(**kw):
    args = dict(num_worlds=3, max_agents=2, episode_steps=91, root_interval=5, window_end=60,
                lstm_layers=1, lstm_hidden=4)
    args.update(kw)
    return RootStore(**args)


def _memory(w: int, a: int, value_of_world: np.ndarray) -> tuple[th.Tensor, th.Tensor]:
    # (layers, W * A, hidden): every entry of world w holds value_of_world[w]
    x = th.as_tensor(np.repeat(value_of_world, a)).float().reshape(1, w * a, 1).expand(1, w * a, 4).clone()
    return x, -x


class Snap:
    """A stand-in snapshot: the store reads only its world count."""

    def __init__(self, n):
        self.num_worlds = n


def test_due_worlds_follow_each_worlds_own_clock():
    s = _store()
    assert s.due(np.array([0, 3, 10])).tolist() == [0, 2]
    assert s.due(np.array([90, 91, 85])).tolist() == [0, 2]  # 91 is past the last decision
    # decision T itself is no decision (0..T-1 are): no root there, even on the interval
    assert _store(episode_steps=90).due(np.array([90, 85, 0])).tolist() == [1, 2]


def test_traces_restart_with_each_episode_and_clamp_at_the_end():
    s = _store()
    s.record_step(np.array([3, 3, 95]), np.arange(6), np.full(6, 0.25), np.arange(6) + 1)
    # a world past its last decision writes the trace's last column, not out of range
    assert s.actions[2, :, 91].tolist() == [5, 6] and s.values[2, 1, 91] == 5.0
    assert s.actions[0, :, 3].tolist() == [1, 2] and s.uniforms[1, 0, 3] == 0.25
    s.new_episodes(np.array([0]))
    assert np.all(s.actions[0] == -1) and np.all(np.isnan(s.uniforms[0]))
    assert s.actions[1, :, 3].tolist() == [3, 4] and s.uniforms[1, 0, 3] == 0.25  # other worlds kept


def test_store_and_request_keep_the_right_world_and_step():
    s = _store()
    for step in range(0, 80, 5):
        worlds = np.array([0, 2])
        snap = {"step": step}
        pi = _memory(3, 2, np.array([step, -1, step + 1000]))
        s.store(worlds, np.array([step, step]), snap, pi, pi, np.full((2, 2, 10), step, np.float32), np.array([2, 1]))
        s.record_step(np.full(3, step), np.arange(6) + step, np.full(6, 0.5), np.zeros(6))
    steps, _ = s.roots_of(0)
    # ring of 60 // 5 + 2 = 14 roots: the oldest were overwritten
    assert sorted(steps.tolist()) == list(range(10, 80, 5))
    req = s.request(2, 1, failure_step=75, outcome=4, root_step=40)
    assert req.snapshot == {"step": 40} and req.snapshot_row == 1
    assert req.depth == 35 and req.deadline == 91
    assert float(req.pi_state[0][0, 1, 0]) == 1040.0 and float(req.pi_state[1][0, 0, 0]) == -1040.0
    assert req.conditions.shape == (2, 10) and req.conditions[0, 0] == 40
    assert req.alive_at_root == 1
    assert req.projected_transitions(7) == 7 * 1 * (91 - 40)
    assert req.values[75] == 2 * 2 + 1 + 75  # world 2, agent 1 -> env index 5
    with pytest.raises(ValueError, match="root_step"):
        s.request(2, 1, 75, 4, root_step=41)


def test_new_episode_hides_old_roots_and_garbage_collection():
    s = _store()
    pi = _memory(3, 2, np.zeros(3))
    s.store(np.array([0, 1]), np.array([0, 0]), "a", pi, pi, np.zeros((2, 2, 10)), np.array([2, 2]))
    s.store(np.array([1]), np.array([5]), "b", pi, pi, np.zeros((1, 2, 10)), np.array([2]))
    s.new_episodes(np.array([1]))
    assert s.roots_of(1)[0].size == 0 and s.roots_of(0)[0].tolist() == [0]
    s.store(np.array([1]), np.array([0]), "c", pi, pi, np.zeros((1, 2, 10)), np.array([2]))  # overwrites ring slot 0
    s.collect_garbage()
    assert sorted(s.snapshots.values()) == ["a", "b", "c"]  # "b" is still referenced by the ring
    s.store(np.array([1]), np.array([5]), "d", pi, pi, np.zeros((1, 2, 10)), np.array([2]))
    s.collect_garbage()
    assert sorted(s.snapshots.values()) == ["a", "c", "d"]


def test_unreferenced_snapshots_are_recycled_by_size():
    s = _store(window_end=5)  # ring of 3
    pi = _memory(3, 2, np.zeros(3))
    first = Snap(2)
    s.store(np.array([0, 1]), np.array([0, 0]), first, pi, pi, np.zeros((2, 2, 10)), np.array([2, 2]))
    for step in (5, 10, 15):  # overwrite every ring slot of worlds 0 and 1
        s.store(np.array([0, 1]), np.array([step, step]), Snap(2), pi, pi, np.zeros((2, 2, 10)), np.array([2, 2]))
    assert s.take_free(2) is None  # nothing collected yet
    s.collect_garbage()
    assert s.take_free(1) is None
    assert s.take_free(2) is first and s.take_free(2) is None


def test_drop_roots_forgets_every_root_and_keeps_pinned_snapshots():
    s = _store(window_end=5)  # ring of 3
    pi = _memory(3, 2, np.zeros(3))
    pinned, other = Snap(2), Snap(2)
    s.store(np.array([0, 1]), np.array([0, 0]), pinned, pi, pi, np.zeros((2, 2, 10)), np.array([2, 2]))
    s.store(np.array([0, 1]), np.array([5, 5]), other, pi, pi, np.zeros((2, 2, 10)), np.array([2, 2]))
    s.drop_roots(pinned=[pinned])
    assert s.roots_of(0)[0].size == 0 and s.roots_of(1)[0].size == 0  # same episode, no root
    assert s.snapshots == {}
    # the pinned snapshot (a queued request still reads it) is not handed out for reuse
    assert s.take_free(2) is other and s.take_free(2) is None


def test_recycled_snapshots_are_bounded_by_the_ring():
    s = _store(window_end=5)  # ring of 3
    pi = _memory(3, 2, np.zeros(3))
    for step in range(0, 30, 5):  # 6 snapshots of world 0, the ring keeps 3
        s.store(np.array([0]), np.array([step]), Snap(1), pi, pi, np.zeros((1, 2, 10)), np.array([2]))
    s.drop_roots()
    assert sum(s.take_free(1) is not None for _ in range(6)) == 3
