"""Batched branch rollouts on a second simulator built on the same scenario pool.

Every branch world starts from a root (a snapshot of one main world), with every agent's
recorded LSTM memory and condition; only the focal agent's condition may differ between
the branches of one search. All branch worlds of all searches of a generation run
together: one policy forward over ``(branch worlds x agents)`` and one simulator step per
decision, until every branch world reaches its original deadline (or has no
decision-making agent left).

Sampling is by the inverse CDF of the policy's categorical distribution with one uniform
per agent per decision, shared by the branches of a search (shared randomness); the
focal agent may get its own draws per branch (ablation), and a caller may pass the draws
(replaying the main rollout's own draws).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import torch as th
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from sb3_contrib.common.recurrent.type_aliases import RNNStates

from cpalgo.common.policy_utils import inverse_cdf_sample, policy_step_logits, put_states, take_states
from cpalgo.counterplay.search import BranchOutcome
from cpsim.config import Outcome

__all__ = ["BranchJob", "BranchResult", "BranchRunner", "GrowingSimulator", "branch_simulator_factory"]

OUTCOME_GOAL = int(Outcome.GOAL)


@dataclass
class BranchJob:
    """One search's branches (or its verification pair) from one root.

    Attributes:
        snapshot, snapshot_row: the root snapshot and the main world's row in it.
        conditions: (B, A, 10) raw conditions of each of the B branch worlds.
        pi_state, vf_state: (h, c), each (layers, A, hidden): memory of every agent at the root.
        focal: focal agent slot.
        root_step: the root decision; deadline: episode length (branches stop there).
        independent_focal: (B,) bool, branches whose focal agent draws its own uniforms.
        uniforms: optional (steps, A) draws to use instead of fresh ones (replay).
        record: keep the focal agent's trajectory of every branch world.
    """

    snapshot: Any
    snapshot_row: int
    conditions: np.ndarray
    pi_state: tuple[th.Tensor, th.Tensor]
    vf_state: tuple[th.Tensor, th.Tensor]
    focal: int
    root_step: int
    deadline: int
    independent_focal: np.ndarray | None = None
    uniforms: np.ndarray | None = None
    record: bool = True

    @property
    def num_branches(self) -> int:
        return int(self.conditions.shape[0])


@dataclass
class BranchResult:
    """What the branch worlds of one job produced.

    Attributes:
        outcomes: one :class:`BranchOutcome` per branch world.
        transitions: (B,) decision-making agent transitions per branch world.
        focal_obs: (B, T, D) focal observations before each decision (teacher view).
        focal_logits: (B, T, n_actions); focal_actions, focal_rewards: (B, T).
        focal_alive: (B, T) bool, the focal agent decided at that step.
        actions: (B, T, A) int64 actions of every agent (-1 after the world ended).
        xy: (B, T + 1, A, 2) positions before each decision and at the end (replay checks).
    """

    outcomes: list[BranchOutcome]
    transitions: np.ndarray
    focal_obs: th.Tensor | None = None
    focal_logits: th.Tensor | None = None
    focal_actions: th.Tensor | None = None
    focal_rewards: th.Tensor | None = None
    focal_alive: th.Tensor | None = None
    actions: np.ndarray | None = None
    xy: np.ndarray | None = None


def branch_simulator_factory(source: Any) -> Callable[[int], Any]:
    """``num_worlds -> Simulator`` on the main simulator's pool, config and device, sharing its
    static Model (no second road grid or pool build)."""
    def make(num_worlds: int) -> Any:
        from cpsim.simulator import Simulator

        pool = getattr(source, "model", None) or source.scenarios
        return Simulator(pool, num_worlds=int(num_worlds), max_agents=int(source.max_agents),
                         config=source.config, device=str(source.device))

    return make


class GrowingSimulator:
    """Owns a second simulator built by ``make_simulator`` and grown by doubling, the frozen
    ``policy`` its worlds run and the torch ``generator`` of their fresh uniforms (seeded 0
    when None): the common part of :class:`BranchRunner` and the baselines'
    ``ContinuationRunner``. ``clip_reward``: clamp each step's focal reward to [-c, c], as
    the learner's rollouts do (the algorithm's ``clip_reward``; None: no clamp)."""

    def __init__(self, make_simulator: Callable[[int], Any], policy: Any, generator: th.Generator | None = None,
                 clip_reward: float | None = None) -> None:
        self.make_simulator = make_simulator
        self.policy = policy
        self.generator = generator if generator is not None else th.Generator().manual_seed(0)
        self.clip_reward = clip_reward
        self._sim: Any = None
        self._capacity = 0

    def focal_reward(self, sim: Any, rows: th.Tensor, focal: th.Tensor, device: Any) -> th.Tensor:
        """The last step's reward of each world's focal agent, clamped as the rollouts are."""
        reward = sim.reward.to(device)[rows, focal].float()
        return reward if self.clip_reward is None else reward.clamp(-self.clip_reward, self.clip_reward)

    def simulator(self, num_worlds: int) -> Any:
        """A branch simulator with at least ``num_worlds`` worlds (grown by doubling)."""
        if self._sim is None or self._capacity < num_worlds:
            capacity = max(1, self._capacity)
            while capacity < num_worlds:
                capacity *= 2
            self._sim = self.make_simulator(capacity)
            self._capacity = capacity
        return self._sim

    def lay_out(self, sizes: np.ndarray) -> tuple[Any, np.ndarray, int]:
        """Worlds for jobs of ``sizes`` (n_jobs,) worlds each, in job order: ``(sim, offsets,
        n_used)``, job k on worlds ``offsets[k]:offsets[k + 1]`` (offsets (n_jobs + 1,)),
        ``n_used`` = ``sizes.sum()`` <= the simulator's ``self._capacity`` worlds."""
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        n_used = int(offsets[-1])
        return self.simulator(n_used), offsets, n_used


class BranchRunner(GrowingSimulator):
    """Runs :class:`BranchJob` lists on a second simulator (see module docstring).

    Args:
        make_simulator: ``num_worlds -> Simulator`` on the main simulator's pool and config.
        policy: the frozen recurrent policy (evaluated under ``th.no_grad``).
        obs_transform: maps raw simulator observations (N, D) to policy input, e.g.
            ``VecNormalize.normalize_obs``; identity by default.
        generator: torch generator of the fresh uniforms.
        clip_reward: see :class:`GrowingSimulator` (CounterPlay's ``clip_reward``).
    """

    def __init__(
        self,
        make_simulator: Callable[[int], Any],
        policy: RecurrentActorCriticPolicy,
        obs_transform: Callable[[th.Tensor], th.Tensor] | None = None,
        generator: th.Generator | None = None,
        clip_reward: float | None = None,
    ) -> None:
        super().__init__(make_simulator, policy, generator, clip_reward)
        self.obs_transform = obs_transform

    # ------------------------------------------------------------------ run
    @th.no_grad()
    def run(self, jobs: Sequence[BranchJob]) -> list[BranchResult]:
        """Run every branch world of every job to its deadline; one result per job."""
        if not jobs:
            return []
        sizes = np.array([j.num_branches for j in jobs], np.int64)
        sim, offsets, n_used = self.lay_out(sizes)
        n_worlds = self._capacity
        a = int(sim.max_agents)
        device = self.policy.device
        t_max = int(max(j.deadline - j.root_step for j in jobs))
        if t_max <= 0:
            raise ValueError("jobs: every root must lie before its deadline")

        self._restore(sim, jobs, offsets)
        states = self._memories(jobs, offsets, n_worlds, a)
        starts = th.zeros(n_worlds * a, device=device)

        # --- per-world bookkeeping
        world_job = np.repeat(np.arange(len(jobs)), sizes)
        world_job_t = th.as_tensor(world_job, device=device)
        focal = np.concatenate([np.full(s, j.focal) for s, j in zip(sizes, jobs)]).astype(np.int64)
        focal_t = th.as_tensor(focal, device=device)
        steps_left = np.repeat([j.deadline - j.root_step for j in jobs], sizes)
        independent = np.concatenate([
            np.zeros(j.num_branches, bool) if j.independent_focal is None else np.asarray(j.independent_focal, bool)
            for j in jobs
        ])
        indep_idx = th.as_tensor(np.flatnonzero(independent), device=device)
        given = [(k, j.uniforms) for k, j in enumerate(jobs) if j.uniforms is not None]
        rows_u = th.arange(n_used, device=device)

        record = any(j.record for j in jobs)
        d = int(sim.obs.shape[-1])
        n_actions = None
        f_obs = th.zeros(n_used, t_max, d, device=device) if record else None
        f_logits = None
        f_actions = th.zeros(n_used, t_max, dtype=th.long, device=device)
        f_rewards = th.zeros(n_used, t_max, device=device)
        f_alive = th.zeros(n_used, t_max, dtype=th.bool, device=device)
        # everything per step stays on the policy's device; the host reads it once at the end
        all_actions = th.full((n_used, t_max, a), -1, dtype=th.long, device=device)
        xy = th.zeros((n_used, t_max + 1, a, 2), device=device)
        transitions = th.zeros(n_used, dtype=th.long, device=device)
        steps_left_t = th.as_tensor(steps_left, device=device)
        running = th.ones(n_used, dtype=th.bool, device=device)
        # on a CPU the network only runs the agents that decide; on a GPU the full batch is
        # cheaper than the host sync an index would cost
        subset = device.type == "cpu"

        for t in range(t_max):
            world_done = sim.world_done.to(device)[:n_used].bool()
            running &= ~world_done & (t < steps_left_t)
            xy[:, t] = sim.xy.to(device)[:n_used]
            if not bool(running.any()):  # the one host sync per step
                break
            deciding = sim.policy_mask.to(device).bool()  # (n_worlds, A)
            deciding[:n_used] &= running[:, None]
            deciding[n_used:] = False
            obs = sim.obs.to(device).float() * deciding[..., None]
            flat = obs.reshape(n_worlds * a, d)
            if self.obs_transform is not None:
                flat = self.obs_transform(flat)
            if subset:
                rows = deciding.reshape(-1).nonzero().squeeze(-1)
                sub_logits, _, sub_states = policy_step_logits(self.policy, flat[rows], take_states(states, rows),
                                                               starts[rows])
                logits = th.zeros(n_worlds * a, sub_logits.shape[-1], device=device)
                logits[rows] = sub_logits
                states = put_states(states, rows, sub_states)
            else:
                logits, _, states = policy_step_logits(self.policy, flat, states, starts)
            if n_actions is None:
                n_actions = int(logits.shape[-1])
                if record:
                    f_logits = th.zeros(n_used, t_max, n_actions, device=device)

            u = self._uniforms(t, len(jobs), a, given, world_job_t, indep_idx, focal_t, n_worlds)
            actions = inverse_cdf_sample(logits, u.reshape(-1)).reshape(n_worlds, a)

            deciding_used = deciding[:n_used]
            transitions += deciding_used.sum(1)
            all_actions[:, t] = th.where(deciding_used, actions[:n_used], -1)
            f_dec = deciding_used[rows_u, focal_t[:n_used]]
            f_alive[:, t] = f_dec
            f_actions[:, t] = actions[rows_u, focal_t[:n_used]]
            if record:
                f_obs[:, t] = flat.reshape(n_worlds, a, d)[rows_u, focal_t[:n_used]]
                f_logits[:, t] = logits.reshape(n_worlds, a, -1)[rows_u, focal_t[:n_used]]

            sim.step(actions)
            f_rewards[:, t] = self.focal_reward(sim, rows_u, focal_t[:n_used], device) * f_dec
        else:
            xy[:, t_max] = sim.xy.to(device)[:n_used]
        all_actions = all_actions.cpu().numpy()
        xy = xy.cpu().numpy()
        transitions = transitions.cpu().numpy().astype(np.int64)

        return self._results(sim, jobs, offsets, transitions, f_obs, f_logits, f_actions, f_rewards, f_alive,
                             all_actions, xy, record)

    # ------------------------------------------------------------------ parts of run
    def _restore(self, sim: Any, jobs: Sequence[BranchJob], offsets: np.ndarray) -> None:
        """Every job's root into its branch worlds (one restore per distinct snapshot) and
        each branch world's conditions."""
        by_snapshot: dict[int, tuple[Any, list[int], list[int]]] = {}
        for k, job in enumerate(jobs):
            entry = by_snapshot.setdefault(id(job.snapshot), (job.snapshot, [], []))
            for b in range(job.num_branches):
                entry[1].append(int(offsets[k] + b))
                entry[2].append(int(job.snapshot_row))
        for snapshot, worlds, rows in by_snapshot.values():
            sim.restore(snapshot, np.asarray(worlds, np.int64), source=np.asarray(rows, np.int64))
        used = np.arange(int(offsets[-1]))
        sim.set_conditions(np.concatenate([j.conditions for j in jobs]).astype(np.float32), worlds=used)

    def _memories(self, jobs: Sequence[BranchJob], offsets: np.ndarray, n_worlds: int, a: int) -> RNNStates:
        """Actor and critic (h, c), each (layers, n_worlds * A, hidden): every branch world
        starts from its job's root memory; spare worlds keep zeros."""
        device = self.policy.device
        layers, _, hidden = jobs[0].pi_state[0].shape

        def memory(which: str, part: int) -> th.Tensor:
            m = th.zeros(layers, n_worlds, a, hidden, device=device)
            for k, job in enumerate(jobs):
                state = getattr(job, which)[part].to(device)
                m[:, offsets[k]:offsets[k + 1]] = state[:, None]
            return m.reshape(layers, n_worlds * a, hidden)

        return RNNStates((memory("pi_state", 0), memory("pi_state", 1)), (memory("vf_state", 0), memory("vf_state", 1)))

    def _uniforms(self, t: int, n_jobs: int, a: int, given: list[tuple[int, np.ndarray]], world_job: th.Tensor,
                  independent: th.Tensor, focal: th.Tensor, n_worlds: int) -> th.Tensor:
        """(n_worlds, A) draws of decision ``t``: one per agent, shared by the branches of a
        job (shared randomness); replayed draws where a job brings them; fresh focal draws
        for the branches in ``independent``; zeros for spare worlds."""
        device = self.policy.device
        u_job = th.rand(n_jobs, a, generator=self.generator).to(device)
        for k, draws in given:
            if t < draws.shape[0]:
                u_job[k] = th.as_tensor(draws[t], device=device, dtype=u_job.dtype)
        u = u_job[world_job]  # (n_used, A)
        if independent.numel():
            fresh = th.rand(int(independent.numel()), generator=self.generator).to(device)
            u[independent, focal[independent]] = fresh
        if n_worlds > u.shape[0]:  # spare worlds of the grown simulator: any action will do
            u = th.cat([u, th.zeros(n_worlds - u.shape[0], a, device=device)])
        return u

    def _results(self, sim: Any, jobs: Sequence[BranchJob], offsets: np.ndarray, transitions: np.ndarray,
                 f_obs: th.Tensor | None, f_logits: th.Tensor | None, f_actions: th.Tensor, f_rewards: th.Tensor,
                 f_alive: th.Tensor, all_actions: np.ndarray, xy: np.ndarray, record: bool) -> list[BranchResult]:
        """One :class:`BranchResult` per job from the branch worlds' final state."""
        n_used = int(offsets[-1])
        outcome = sim.outcome.detach().cpu().numpy()[:n_used]
        metrics = {k: v.detach().cpu().numpy()[:n_used] for k, v in sim.metrics.items()}
        present = sim.agent_index.detach().cpu().numpy()[:n_used] >= 0 if hasattr(sim.agent_index, "detach") \
            else np.asarray(sim.agent_index)[:n_used] >= 0
        returns = f_rewards.sum(1).cpu().numpy()
        results: list[BranchResult] = []
        for k, job in enumerate(jobs):
            lo, hi = int(offsets[k]), int(offsets[k + 1])
            outs = []
            for i in range(lo, hi):
                completed = bool(outcome[i, job.focal] == OUTCOME_GOAL)
                outs.append(BranchOutcome(
                    focal=job.focal,
                    completed=completed,
                    arrival_step=int(metrics["goal_step"][i, job.focal]) if completed else -1,
                    first_collision_step=metrics["first_collision_step"][i],
                    first_offroad_step=metrics["first_offroad_step"][i],
                    present=present[i],
                    focal_return=float(returns[i]),
                ))
            results.append(BranchResult(
                outcomes=outs,
                transitions=transitions[lo:hi].copy(),
                focal_obs=f_obs[lo:hi] if (record and job.record) else None,
                focal_logits=f_logits[lo:hi] if (record and job.record and f_logits is not None) else None,
                focal_actions=f_actions[lo:hi],
                focal_rewards=f_rewards[lo:hi],
                focal_alive=f_alive[lo:hi],
                actions=all_actions[lo:hi],
                xy=xy[lo:hi],
            ))
        return results
