"""Roots and per-episode traces recorded during the main rollout.

A *root* of world ``w`` at decision ``t`` (``t % root_interval == 0``) is a simulator
snapshot of that world taken before the decision, plus every agent's actor and critic
LSTM memory (after the episode-start reset) and condition. Roots live in a per-world ring
of ``window_end // root_interval + 2`` entries: a failure is handled right after it
happens, so it never needs a root deeper than the window.

Per-episode traces (W, A, T + 1) keep every agent's critic value, the uniform draw used to
sample its action and the action itself at each decision of the world's current episode.
All updates are vectorised over worlds and agents.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch as th

__all__ = ["RootStore", "SearchRequest"]


@dataclass
class SearchRequest:
    """One failed task waiting for its search at the end of the generation.

    Attributes:
        world, focal: main-simulator world and agent slot of the failed task.
        episode: the world's episode id.
        failure_step: the focal agent's last decision; outcome: its ``Outcome`` code.
        root_step: decision of the chosen root; depth = failure_step - root_step.
        snapshot, snapshot_row: the root's simulator snapshot and the row of this world in it.
        pi_state, vf_state: (h, c), each (layers, A, hidden): every agent's memory at the root.
        conditions: (A, 10) raw conditions of every agent at the root.
        alive_at_root: decision-making agents alive at the root (budget projection).
        deadline: the episode's last decision + 1 (branches run until then).
        values: (failure_step + 1,) focal critic values (kept for diagnostics).
    """

    world: int
    focal: int
    episode: int
    failure_step: int
    outcome: int
    root_step: int
    snapshot: Any
    snapshot_row: int
    pi_state: tuple[th.Tensor, th.Tensor]
    vf_state: tuple[th.Tensor, th.Tensor]
    conditions: np.ndarray
    alive_at_root: int
    deadline: int
    values: np.ndarray

    @property
    def depth(self) -> int:
        return self.failure_step - self.root_step

    def projected_transitions(self, num_branch_worlds: int) -> int:
        """Upper bound of agent transitions of ``num_branch_worlds`` branches of this search."""
        return int(num_branch_worlds) * int(self.alive_at_root) * max(0, self.deadline - self.root_step)


class RootStore:
    """Ring of roots per world plus per-episode traces (see module docstring).

    Args:
        num_worlds, max_agents: W, A of the main simulator (env index = w * A + a).
        episode_steps: decisions per episode T.
        root_interval: decisions between roots.
        window_end: deepest backtracking depth needed (decisions).
        lstm_layers, lstm_hidden: LSTM shape of the policy.
        device: torch device of the stored memories.
    """

    def __init__(
        self,
        num_worlds: int,
        max_agents: int,
        episode_steps: int,
        root_interval: int,
        window_end: int,
        lstm_layers: int,
        lstm_hidden: int,
        device: th.device | str = "cpu",
    ) -> None:
        w, a = int(num_worlds), int(max_agents)
        self.num_worlds, self.max_agents = w, a
        self.episode_steps = int(episode_steps)
        self.root_interval = int(root_interval)
        self.ring = int(window_end) // self.root_interval + 2
        self.device = th.device(device)
        r = self.ring
        self.root_step = np.full((w, r), -1, np.int64)
        self.root_episode = np.full((w, r), -1, np.int64)
        self.root_alive = np.zeros((w, r), np.int64)
        self.snapshot_id = np.full((w, r), -1, np.int64)
        self.snapshot_row = np.zeros((w, r), np.int64)
        self.conditions = np.zeros((w, r, a, 10), np.float32)
        shape = (w, r, lstm_layers, a, lstm_hidden)
        self.pi_h = th.zeros(shape, device=self.device)
        self.pi_c = th.zeros(shape, device=self.device)
        self.vf_h = th.zeros(shape, device=self.device)
        self.vf_c = th.zeros(shape, device=self.device)
        self.snapshots: dict[int, Any] = {}
        # snapshots no root refers to any more, by number of worlds: reused through
        # ``Simulator.snapshot(worlds, out=...)`` instead of allocating device storage again
        self._free: dict[int, list[Any]] = {}
        self._next_snapshot_id = 0
        self.episode = np.zeros(w, np.int64)
        t = self.episode_steps + 1
        self.values = np.zeros((w, a, t), np.float32)
        self.uniforms = np.full((w, a, t), np.nan, np.float32)
        self.actions = np.full((w, a, t), -1, np.int64)

    # ------------------------------------------------------------------ recording
    def due(self, step_count: np.ndarray) -> np.ndarray:
        """Worlds whose current decision is a root decision: (k,) int indices."""
        steps = np.asarray(step_count, np.int64)
        return np.flatnonzero((steps % self.root_interval == 0) & (steps < self.episode_steps))

    def store(
        self,
        worlds: np.ndarray,
        steps: np.ndarray,
        snapshot: Any,
        lstm_pi: tuple[th.Tensor, th.Tensor],
        lstm_vf: tuple[th.Tensor, th.Tensor],
        conditions: np.ndarray,
        alive_count: np.ndarray,
    ) -> None:
        """Store roots of ``worlds`` (k,) taken at decisions ``steps`` (k,).

        ``snapshot`` holds these worlds in this order (row i = worlds[i]); ``lstm_pi`` and
        ``lstm_vf`` are the full (layers, W * A, hidden) memories about to be used for
        this decision (already reset on episode starts); ``conditions`` (k, A, 10) raw;
        ``alive_count`` (k,) decision-making agents alive per world.
        """
        worlds = np.asarray(worlds, np.int64)
        if worlds.size == 0:
            return
        steps = np.asarray(steps, np.int64)
        pos = (steps // self.root_interval) % self.ring
        sid = self._next_snapshot_id
        self._next_snapshot_id += 1
        self.snapshots[sid] = snapshot
        self.root_step[worlds, pos] = steps
        self.root_episode[worlds, pos] = self.episode[worlds]
        self.root_alive[worlds, pos] = alive_count
        self.snapshot_id[worlds, pos] = sid
        self.snapshot_row[worlds, pos] = np.arange(worlds.size)
        self.conditions[worlds, pos] = conditions
        layers, _, hidden = lstm_pi[0].shape
        wi = th.as_tensor(worlds, device=self.device)
        pi = th.as_tensor(pos, device=self.device)

        def per_world(x: th.Tensor) -> th.Tensor:  # (layers, W*A, hidden) -> (k, layers, A, hidden)
            x = x.reshape(layers, self.num_worlds, self.max_agents, hidden)[:, wi]
            return x.permute(1, 0, 2, 3).to(self.device)

        self.pi_h[wi, pi] = per_world(lstm_pi[0])
        self.pi_c[wi, pi] = per_world(lstm_pi[1])
        self.vf_h[wi, pi] = per_world(lstm_vf[0])
        self.vf_c[wi, pi] = per_world(lstm_vf[1])

    def record_step(self, step_count: np.ndarray, values: np.ndarray, uniforms: np.ndarray | None,
                    actions: np.ndarray) -> None:
        """Write one decision of every world: values / uniforms / actions are (W * A,)."""
        w, a = self.num_worlds, self.max_agents
        t = np.minimum(np.asarray(step_count, np.int64), self.episode_steps)
        rows = np.arange(w)
        self.values[rows, :, t] = np.asarray(values, np.float32).reshape(w, a)
        if uniforms is not None:
            self.uniforms[rows, :, t] = np.asarray(uniforms, np.float32).reshape(w, a)
        self.actions[rows, :, t] = np.asarray(actions, np.int64).reshape(w, a)

    def new_episodes(self, worlds: np.ndarray) -> None:
        """Worlds that were reset: their old roots and traces stop being usable."""
        worlds = np.asarray(worlds, np.int64)
        if worlds.size:
            self.episode[worlds] += 1
            self.uniforms[worlds] = np.nan
            self.actions[worlds] = -1

    def invalidate(self) -> None:
        """After an external reset of every world (``env.reset()``)."""
        self.new_episodes(np.arange(self.num_worlds))

    def drop_roots(self, pinned: list[Any] | tuple[Any, ...] = ()) -> None:
        """A new generation starts: every stored root stops being usable.

        Only with ``root_lifetime="generation"`` (otherwise a root lives until its episode
        ends): roots then belong to the generation that recorded them, so a root choice
        never mixes the values of two critics. Snapshots in ``pinned`` (still needed by
        queued requests) are not recycled.
        """
        self.root_step[:] = -1
        self.snapshot_id[:] = -1
        self.collect_garbage(pinned=pinned)

    # ------------------------------------------------------------------ search requests
    def roots_of(self, world: int) -> tuple[np.ndarray, np.ndarray]:
        """(root decisions, ring positions) of ``world``'s current episode."""
        ok = (self.root_episode[world] == self.episode[world]) & (self.root_step[world] >= 0)
        pos = np.flatnonzero(ok)
        return self.root_step[world, pos], pos

    def request(self, world: int, focal: int, failure_step: int, outcome: int, root_step: int) -> SearchRequest:
        """Freeze what a search from ``root_step`` needs (the ring may be overwritten later)."""
        steps, positions = self.roots_of(world)
        match = positions[steps == root_step]
        if match.size == 0:
            raise ValueError(f"root_step: no root at decision {root_step} in world {world}'s episode")
        p = int(match[0])
        sid = int(self.snapshot_id[world, p])
        return SearchRequest(
            world=int(world),
            focal=int(focal),
            episode=int(self.episode[world]),
            failure_step=int(failure_step),
            outcome=int(outcome),
            root_step=int(root_step),
            snapshot=self.snapshots[sid],
            snapshot_row=int(self.snapshot_row[world, p]),
            pi_state=(self.pi_h[world, p].clone(), self.pi_c[world, p].clone()),
            vf_state=(self.vf_h[world, p].clone(), self.vf_c[world, p].clone()),
            conditions=self.conditions[world, p].copy(),
            alive_at_root=int(self.root_alive[world, p]),
            deadline=self.episode_steps,
            values=self.values[world, focal, : failure_step + 1].copy(),
        )

    def collect_garbage(self, recycle: bool = True, pinned: list[Any] | tuple[Any, ...] = ()) -> None:
        """Drop snapshots no ring entry refers to any more.

        With ``recycle`` the dropped snapshots are kept for reuse by :meth:`take_free`,
        except those in ``pinned``: a queued :class:`SearchRequest` still reads them.
        """
        live = set(np.unique(self.snapshot_id[self.snapshot_id >= 0]).tolist())
        keep = {id(snap) for snap in pinned}
        for sid in list(self.snapshots):
            if sid not in live:
                snap = self.snapshots.pop(sid)
                n = getattr(snap, "num_worlds", None)
                if recycle and isinstance(n, int) and id(snap) not in keep:
                    pool = self._free.setdefault(n, [])
                    if len(pool) < self.ring:  # bounded: never more than one ring's worth
                        pool.append(snap)

    def take_free(self, num_worlds: int) -> Any | None:
        """A recycled snapshot holding ``num_worlds`` worlds, or None."""
        pool = self._free.get(int(num_worlds))
        return pool.pop() if pool else None
