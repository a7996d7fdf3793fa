"""The focal critic value along failed episodes, and the roots the value rule picks from it.

The checkpoint drives ``--tasks`` procedural training tasks under p_train conditions (every
agent a POLICY agent, sampled actions, as in self-play). For every POLICY agent it records the
critic value at each decision. It prints, per outcome class, the mean value (and the mean discounted return actually
received) at 0, 5, ..., 60 decisions before the agent's last decision, the weighted reward terms summed over its episode,
and the depths that
:func:`cpalgo.counterplay.search.select_root` picks for the failures (roots every 5 decisions,
window 5-60, rho 0.5, as the post-training recipe).

    python docs/results/anchor_failures/value_trace.py zoo/anchor.zip --tasks 96
"""

from __future__ import annotations

import argparse
import collections

import numpy as np
import torch as th

from cpalgo.common.policy_utils import inverse_cdf_sample, policy_step_logits, zero_states
from cpalgo.counterplay.search import select_root
from cpalgo.evaluate.runner import load_model
from cpalgo.pretrain import _policy_obs
from cpsim.conditions import sample_conditions
from cpsim.config import Controller, Outcome, SimConfig
from cpsim.scenario.procedural import train_pool
from cpsim.simulator import Simulator
from cpsim.state import REWARD_TERMS

DEPTHS = list(range(0, 65, 5))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("model", help="a checkpoint .zip")
    parser.add_argument("--tasks", type=int, default=96)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rho", type=float, default=0.5)
    parser.add_argument("--gamma", type=float, default=0.99)
    args = parser.parse_args()
    th.set_num_threads(1)
    policy = load_model(args.model, "model").policy
    policy.set_training_mode(False)
    W, A = args.tasks, 8
    config = SimConfig()
    sim = Simulator(train_pool(W, seed=args.seed), num_worlds=W, max_agents=A, config=config, seed=args.seed)
    cond = sample_conditions(np.random.default_rng(args.seed), (W, A)).astype(np.float32)
    sim.reset(scenario_index=np.arange(W), conditions=cond)
    gen = th.Generator().manual_seed(args.seed)
    states = zero_states(policy, W * A, policy.device)
    starts = th.ones(W * A)
    policy_slots = (sim.controllers == int(Controller.POLICY)).cpu().numpy()
    values, alive, rewards, terms = [], [], [], []
    with th.no_grad():
        for _ in range(config.episode_steps):
            logits, v, states = policy_step_logits(policy, _policy_obs(sim), states, starts)
            starts = th.zeros_like(starts)
            values.append(v.reshape(W, A).numpy().copy())
            alive.append((sim.alive.cpu().numpy() & policy_slots).copy())
            act = inverse_cdf_sample(logits, th.rand(W * A, generator=gen))
            sim.step(act.reshape(W, A).to(th.int32))
            rewards.append(sim.reward.cpu().numpy().copy())
            terms.append(np.stack([sim.reward_terms[f"w_{n}"].cpu().numpy() for n in REWARD_TERMS], -1))
            if bool(sim.world_done.all()):
                break
    values, alive = np.stack(values), np.stack(alive)  # (T, W, A)
    rewards = np.where(alive, np.stack(rewards), 0.0)
    returns = np.zeros_like(rewards)  # discounted return from each decision, gamma of the recipe
    running = np.zeros(rewards.shape[1:])
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = rewards[t] + args.gamma * running
        returns[t] = running
    outcome = sim.outcome.cpu().numpy()
    ever = alive.any(0)
    last = np.where(ever, alive.shape[0] - 1 - np.argmax(alive[::-1], axis=0), -1)
    roots = np.arange(0, values.shape[0], 5)
    print(f"{args.model}: {int(ever.sum())} policy agents, {values.shape[0]} decisions")
    print("critic value V (discounted return G) at d decisions before the agent's last decision")
    print("| outcome | agents | mean last decision | " + " | ".join(f"-{d}" for d in DEPTHS) + " |")
    print("|---|---|---|" + "---|" * len(DEPTHS))
    picked = collections.defaultdict(list)
    for kind in (Outcome.GOAL, Outcome.TIMEOUT, Outcome.COLLISION, Outcome.OFFROAD):
        sel = [(w, a) for w, a in zip(*np.nonzero(ever)) if outcome[w, a] == int(kind)]
        if not sel:
            continue
        cells = []
        for d in DEPTHS:
            ok = [(w, a) for w, a in sel if last[w, a] - d >= 0]
            vals = [values[last[w, a] - d, w, a] for w, a in ok]
            rets = [returns[last[w, a] - d, w, a] for w, a in ok]
            cells.append(f"{np.mean(vals):.2f} ({np.mean(rets):.2f})" if vals else "-")
        print(f"| {kind.name.lower()} | {len(sel)} | {np.mean([last[w, a] for w, a in sel]):.1f} | "
              + " | ".join(cells) + " |")
        if kind != Outcome.GOAL:
            for w, a in sel:
                r = select_root(values[:, w, a], roots, int(last[w, a]), (5, 60), args.rho)
                if r is not None:
                    picked[kind.name.lower()].append(int(last[w, a]) - r)
    terms = np.where(alive[..., None], np.stack(terms), 0.0)  # (T, W, A, terms), weighted
    print("weighted reward terms summed over an episode, mean per agent")
    print("| outcome | " + " | ".join(REWARD_TERMS) + " |")
    print("|---|" + "---|" * len(REWARD_TERMS))
    for kind in (Outcome.GOAL, Outcome.TIMEOUT, Outcome.COLLISION, Outcome.OFFROAD):
        sel = ever & (outcome == int(kind))
        if sel.any():
            per_agent = terms.sum(0)[sel]  # (n, terms)
            print(f"| {kind.name.lower()} | " + " | ".join(f"{x:.3f}" for x in per_agent.mean(0)) + " |")
    for kind, depths in picked.items():
        hist = collections.Counter(depths)
        print(f"{kind}: value-rule depth mean {np.mean(depths):.1f}, median {np.median(depths):.0f}; "
              + ", ".join(f"{d}: {hist[d]}" for d in sorted(hist)))


if __name__ == "__main__":
    main()
