"""Search yield of a driver at fixed root depths: how many failed tasks one CounterPlay search
could repair if it were driven by this driver.

The driver (a ``cpsim.expert`` teacher name or a checkpoint ``.zip``) drives ``--tasks``
procedural training tasks under p_train conditions (every agent a POLICY agent of its world,
as in self-play), with a snapshot of every world (and the checkpoint's recurrent memory) every
5 decisions. For every failed POLICY agent (timeout, collision or off-road) and every depth
``d`` of ``--depths``, the root is the stored root nearest to ``d`` decisions before its last
decision; from there one factual branch (the focal agent's own condition) and the five panel
styles (style fields swapped, task fields kept; every other agent keeps its condition) are
driven to the deadline, with the search's own tests (:func:`cpalgo.counterplay.search.admit`):
a retry is admissible when the focal agent completes, it outranks the factual branch and no
other vehicle gets a new or earlier collision / off-road.

A teacher is deterministic. A checkpoint samples by the inverse CDF with draws shared by the
branches of a search, as CounterPlay's search does (``--argmax`` for its argmax actions).

    python docs/results/anchor_failures/search_yield.py reactive
    python docs/results/anchor_failures/search_yield.py zoo/anchor.zip

Reports, per failure class and depth: searches, admissible share, admissible retries per
search, and the styles that won. About 3 min on one core for 192 tasks.
"""

from __future__ import annotations

import argparse
import collections
import time

import numpy as np
import torch as th
from sb3_contrib.common.recurrent.type_aliases import RNNStates

from cpalgo.common.policy_utils import inverse_cdf_sample, policy_step_logits, zero_states
from cpalgo.counterplay.search import BranchOutcome, admit, rank_branches
from cpalgo.evaluate.runner import load_model
from cpalgo.pretrain import _policy_obs
from cpsim.conditions import PANEL, PROFILES, STYLE_MASK, sample_conditions
from cpsim.config import Controller, Outcome, SimConfig
from cpsim.expert import make_expert
from cpsim.scenario.procedural import train_pool
from cpsim.simulator import Simulator

ROOT_INTERVAL = 5
FAILURES = {int(Outcome.TIMEOUT): "timeout", int(Outcome.COLLISION): "collision", int(Outcome.OFFROAD): "offroad"}


class Driver:
    """Actions of every slot of a simulator: a teacher, or a checkpoint with its memory."""

    def __init__(self, name: str, argmax: bool) -> None:
        self.name = name
        self.argmax = argmax
        self.policy = None
        if name.endswith(".zip"):
            self.policy = load_model(name, "driver").policy
            self.policy.set_training_mode(False)

    def bind(self, sim: Simulator, memory=None) -> None:
        """Drive ``sim`` from here on (memory: RNNStates for its W*A slots, or zeros)."""
        self.sim = sim
        if self.policy is None:
            self.expert = make_expert(self.name, sim)
            return
        n = sim.num_worlds * sim.max_agents
        self.states = memory if memory is not None else zero_states(self.policy, n, self.policy.device)
        self.starts = th.full((n,), 0.0 if memory is not None else 1.0)

    @th.no_grad()
    def actions(self, uniforms: th.Tensor | None) -> th.Tensor:
        """(W, A) int32 actions; ``uniforms`` (W, A) are the draws of a sampling checkpoint."""
        if self.policy is None:
            return self.expert.actions()
        sim = self.sim
        logits, _, self.states = policy_step_logits(self.policy, _policy_obs(sim), self.states, self.starts)
        self.starts = th.zeros_like(self.starts)
        if self.argmax or uniforms is None:
            act = logits.argmax(-1)
        else:
            act = inverse_cdf_sample(logits, uniforms.reshape(-1))
        return act.reshape(sim.num_worlds, sim.max_agents).to(th.int32)


def memory_rows(states, rows: np.ndarray):
    """The RNNStates of the given slot rows (a copy)."""
    idx = th.as_tensor(rows, dtype=th.long)
    return RNNStates(tuple(s[:, idx].clone() for s in states.pi), tuple(s[:, idx].clone() for s in states.vf))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("driver", help="a cpsim.expert name or a checkpoint .zip")
    parser.add_argument("--tasks", type=int, default=192)
    parser.add_argument("--depths", type=int, nargs="+", default=[10, 30, 50])
    parser.add_argument("--argmax", action="store_true", help="argmax actions of a checkpoint")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--chunk", type=int, default=1200, help="branch worlds per batch")
    args = parser.parse_args()
    th.set_num_threads(1)
    t_start = time.time()
    scenarios = train_pool(args.tasks, seed=args.seed)
    W, A = args.tasks, 8
    config = SimConfig()
    sim = Simulator(scenarios, num_worlds=W, max_agents=A, config=config, seed=args.seed)
    rng = np.random.default_rng(args.seed)
    cond = sample_conditions(rng, (W, A)).astype(np.float32)
    sim.reset(scenario_index=np.arange(W), conditions=cond)
    gen = th.Generator().manual_seed(args.seed)
    driver = Driver(args.driver, args.argmax)
    driver.bind(sim)
    policy_slots = (sim.controllers == int(Controller.POLICY)).cpu().numpy()
    T = config.episode_steps
    snapshots, memories, alive = {}, {}, []
    for t in range(T):
        if t % ROOT_INTERVAL == 0:
            snapshots[t] = sim.snapshot(np.arange(W))
            if driver.policy is not None:
                memories[t] = memory_rows(driver.states, np.arange(W * A))
        alive.append((sim.alive.cpu().numpy() & policy_slots).copy())
        sim.step(driver.actions(th.rand(W, A, generator=gen)))
        if bool(sim.world_done.all()):
            break
    alive = np.stack(alive)  # (T', W, A)
    outcome = sim.outcome.cpu().numpy()
    ever = alive.any(0)
    last = np.where(ever, alive.shape[0] - 1 - np.argmax(alive[::-1], axis=0), -1)
    counts = collections.Counter(outcome[ever].tolist())
    print(f"{args.driver}: {int(ever.sum())} policy agents; outcomes "
          + ", ".join(f"{Outcome(k).name.lower()} {v / ever.sum():.1%}" for k, v in sorted(counts.items())))
    failures = [(w, a, FAILURES[int(outcome[w, a])], int(last[w, a]))
                for w, a in zip(*np.nonzero(ever)) if int(outcome[w, a]) in FAILURES]

    # one search = (failure, depth): branch 0 factual, then the panel
    searches = []
    for w, a, kind, fail in failures:
        for d in args.depths:
            root = int(round((fail - d) / ROOT_INTERVAL)) * ROOT_INTERVAL
            root = min(root, (fail - 1) // ROOT_INTERVAL * ROOT_INTERVAL)
            if root < 0:
                continue
            searches.append((w, a, kind, fail, d, root))
    B = 1 + len(PANEL)
    results = collections.defaultdict(list)  # (kind, depth) -> [(n admissible, winner)]
    per_chunk = max(1, args.chunk // B)
    branch_sim = None
    for lo in range(0, len(searches), per_chunk):
        part = searches[lo:lo + per_chunk]
        n_worlds = len(part) * B
        if branch_sim is None or branch_sim.num_worlds != n_worlds:
            branch_sim = Simulator(scenarios, num_worlds=n_worlds, max_agents=A, config=config, seed=args.seed)
        by_root = collections.defaultdict(list)
        for k, (w, *_, root) in enumerate(part):
            by_root[root].extend((k * B + b, w) for b in range(B))
        for root, pairs in by_root.items():
            worlds, rows = zip(*pairs)
            branch_sim.restore(snapshots[root], np.asarray(worlds), source=np.asarray(rows))
        conds = np.repeat(np.stack([cond[w] for w, *_ in part]), B, axis=0)  # (n_worlds, A, 10)
        for k, (_, a, *_rest) in enumerate(part):
            for j, style in enumerate(PANEL, start=1):
                conds[k * B + j, a, STYLE_MASK] = PROFILES[style][STYLE_MASK]
        branch_sim.set_conditions(conds)
        memory = None
        if driver.policy is not None:
            parts = [memory_rows(memories[root], np.arange(w * A, (w + 1) * A)) for w, *_, root in part]

            def cat(which: str, i: int, parts=parts) -> th.Tensor:
                # (layers, A, hidden) per search -> its B branch worlds in order
                return th.cat([getattr(p, which)[i].repeat(1, B, 1) for p in parts], dim=1)

            memory = RNNStates((cat("pi", 0), cat("pi", 1)), (cat("vf", 0), cat("vf", 1)))
        driver.bind(branch_sim, memory)
        steps = T - min(p[5] for p in part)
        for _ in range(steps):
            u = th.rand(len(part), A, generator=gen).repeat_interleave(B, dim=0)  # shared per search
            branch_sim.step(driver.actions(u))
            if bool(branch_sim.world_done.all()):
                break
        b_out = branch_sim.outcome.cpu().numpy()
        metrics = {k: v.cpu().numpy() for k, v in branch_sim.metrics.items()}
        present = branch_sim.agent_index.cpu().numpy() >= 0
        for k, (_, a, kind, _fail, d, _root) in enumerate(part):
            outs = []
            for b in range(B):
                i = k * B + b
                done = bool(b_out[i, a] == int(Outcome.GOAL))
                outs.append(BranchOutcome(
                    focal=a, completed=done, arrival_step=int(metrics["goal_step"][i, a]) if done else -1,
                    first_collision_step=metrics["first_collision_step"][i],
                    first_offroad_step=metrics["first_offroad_step"][i], present=present[i]))
            ok = [admit(outs[0], o) for o in outs[1:]]
            winner = None
            if any(ok):
                order = rank_branches([o.completed for o in outs[1:]], [o.n_harmed for o in outs[1:]],
                                      [o.arrival_step for o in outs[1:]])
                winner = next(PANEL[j] for j in order if ok[j])
            results[(kind, d)].append((sum(ok), winner, outs[0].completed))
    print(f"{len(failures)} failures, {len(searches)} searches, {time.time() - t_start:.0f} s")
    print("| failure | depth | searches | factual rerun completes | admissible share | admissible retries / search | winners |")
    print("|---|---|---|---|---|---|---|")
    for kind in ("timeout", "collision", "offroad", "all"):
        for d in args.depths:
            rows = [r for (k, dd), rs in results.items() if dd == d and (k == kind or kind == "all") for r in rs]
            if not rows:
                continue
            wins = collections.Counter(r[1] for r in rows if r[1] is not None)
            print(f"| {kind} | {d} | {len(rows)} | {np.mean([r[2] for r in rows]):.1%} | "
                  f"{np.mean([r[0] > 0 for r in rows]):.1%} | {np.mean([r[0] for r in rows]):.2f} | "
                  + ", ".join(f"{s} {n}" for s, n in wins.most_common()) + " |")


if __name__ == "__main__":
    main()
