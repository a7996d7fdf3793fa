"""The critic asked about another driving style: does it then track the task?

The critic is reward-conditioned: asked at the same state under the aggressive profile
(comfort 0, tiny lane terms, collision 0.2) it should estimate a return made almost only of
the goal. This script drives ``--tasks`` procedural training tasks under p_train (every agent
a POLICY agent, sampled actions), records at every decision the critic value under the
agent's own condition and under ``--profile`` (style fields of the observation swapped, task
fields kept; the critic of the shipped anchor is memoryless, so nothing else changes), and
prints both before the last decision per outcome, and the depths the value rule (roots every
5 decisions, window 5-60, rho 0.5) picks from each.

    python docs/results/critic_refit/value_under_profile.py zoo/anchor.zip --tasks 96
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
from cpsim.conditions import STYLE_MASK, normalize_condition, profile, sample_conditions
from cpsim.config import Controller, Outcome, SimConfig
from cpsim.observation import EGO_FEATURES
from cpsim.scenario.procedural import train_pool
from cpsim.simulator import Simulator

DEPTHS = list(range(0, 65, 5))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("model")
    parser.add_argument("--tasks", type=int, default=96)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--profile", default="aggressive")
    args = parser.parse_args()
    th.set_num_threads(1)
    policy = load_model(args.model, "model").policy
    policy.set_training_mode(False)
    W, A = args.tasks, 8
    config = SimConfig()
    sim = Simulator(train_pool(W, seed=args.seed), num_worlds=W, max_agents=A, config=config, seed=args.seed)
    sim.reset(scenario_index=np.arange(W),
              conditions=sample_conditions(np.random.default_rng(args.seed), (W, A)).astype(np.float32))
    cols = th.as_tensor(np.arange(EGO_FEATURES, EGO_FEATURES + STYLE_MASK.size)[STYLE_MASK])
    style = th.as_tensor(normalize_condition(profile(args.profile))[STYLE_MASK], dtype=th.float32)
    gen = th.Generator().manual_seed(args.seed)
    states = zero_states(policy, W * A, policy.device)
    starts = th.ones(W * A)
    policy_slots = (sim.controllers == int(Controller.POLICY)).cpu().numpy()
    own, other, alive = [], [], []
    with th.no_grad():
        for _ in range(config.episode_steps):
            obs = _policy_obs(sim)
            swapped = obs.clone()
            live = (obs.abs().sum(-1) > 0).nonzero().squeeze(-1)
            swapped[live[:, None], cols] = style
            _, v_other, _ = policy_step_logits(policy, swapped, states, starts)
            logits, v, states = policy_step_logits(policy, obs, states, starts)
            starts = th.zeros_like(starts)
            own.append(v.reshape(W, A).numpy().copy())
            other.append(v_other.reshape(W, A).numpy().copy())
            alive.append((sim.alive.cpu().numpy() & policy_slots).copy())
            sim.step(inverse_cdf_sample(logits, th.rand(W * A, generator=gen)).reshape(W, A).to(th.int32))
            if bool(sim.world_done.all()):
                break
    own, other, alive = np.stack(own), np.stack(other), np.stack(alive)
    outcome = sim.outcome.cpu().numpy()
    ever = alive.any(0)
    last = np.where(ever, alive.shape[0] - 1 - np.argmax(alive[::-1], axis=0), -1)
    roots = np.arange(0, own.shape[0], 5)
    print(f"{args.model}: {int(ever.sum())} policy agents; critic value under the own condition "
          f"(under {args.profile}) at d decisions before the agent's last decision")
    print("| outcome | agents | " + " | ".join(f"-{d}" for d in DEPTHS) + " |")
    print("|---|---|" + "---|" * len(DEPTHS))
    for kind in (Outcome.GOAL, Outcome.TIMEOUT, Outcome.COLLISION, Outcome.OFFROAD):
        sel = [(w, a) for w, a in zip(*np.nonzero(ever)) if outcome[w, a] == int(kind)]
        if not sel:
            continue
        cells = []
        for d in DEPTHS:
            ok = [(w, a) for w, a in sel if last[w, a] - d >= 0]
            cells.append(f"{np.mean([own[last[w, a] - d, w, a] for w, a in ok]):.2f} "
                         f"({np.mean([other[last[w, a] - d, w, a] for w, a in ok]):.2f})" if ok else "-")
        print(f"| {kind.name.lower()} | {len(sel)} | " + " | ".join(cells) + " |")
    for kind in (Outcome.TIMEOUT, Outcome.COLLISION):
        sel = [(w, a) for w, a in zip(*np.nonzero(ever)) if outcome[w, a] == int(kind)]
        for name, trace in (("the own condition", own), (args.profile, other)):
            depths = [int(last[w, a]) - r for w, a in sel
                      if (r := select_root(trace[:, w, a], roots, int(last[w, a]))) is not None]
            hist = collections.Counter(depths)
            print(f"{kind.name.lower()}, value under {name}: depth mean {np.mean(depths):.1f}, "
                  f"median {np.median(depths):.0f}; <= 10 back {sum(hist[d] for d in hist if d <= 10)}, "
                  f"60 back {hist[60]}")


if __name__ == "__main__":
    main()
