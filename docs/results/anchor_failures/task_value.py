"""Would a value of the task alone give the value rule deeper roots? An offline check.

``value_trace.py`` shows that the critic's value (and the return) of every agent rises
towards the end of its episode, because the per-step style penalties are as large as the goal
reward. This script fits a *task value* instead: a memoryless MLP (the anchor's observation,
condition included -> 1) regressed on the discounted return of the task terms alone (goal,
collision and off-road, gamma 0.99, a timeout returns 0), on the checkpoint's own rollouts of
``--fit-seeds`` (each ``--tasks`` procedural training tasks under p_train, sampled actions).
On a held-out rollout (``--seed``) it prints the mean task value before the last decision per
outcome class and the depths that :func:`cpalgo.counterplay.search.select_root` picks from it
(window 5-60, rho 0.5), next to those it picks from the critic's value.

    python docs/results/anchor_failures/task_value.py zoo/anchor.zip
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

TASK_TERMS = ("w_goal", "w_collision", "w_offroad")
DEPTHS = list(range(0, 65, 5))


def rollout(policy, tasks: int, seed: int, gamma: float) -> dict[str, np.ndarray]:
    """One episode of ``tasks`` worlds: obs (T, W, A, D), alive, critic values, task returns,
    outcome (W, A), last decision (W, A)."""
    W, A = tasks, 8
    config = SimConfig()
    sim = Simulator(train_pool(W, seed=seed), num_worlds=W, max_agents=A, config=config, seed=seed)
    sim.reset(scenario_index=np.arange(W),
              conditions=sample_conditions(np.random.default_rng(seed), (W, A)).astype(np.float32))
    gen = th.Generator().manual_seed(seed)
    states = zero_states(policy, W * A, policy.device)
    starts = th.ones(W * A)
    policy_slots = (sim.controllers == int(Controller.POLICY)).cpu().numpy()
    obs, alive, values, task_r = [], [], [], []
    with th.no_grad():
        for _ in range(config.episode_steps):
            o = _policy_obs(sim)
            logits, v, states = policy_step_logits(policy, o, states, starts)
            starts = th.zeros_like(starts)
            obs.append(o.reshape(W, A, -1).numpy().astype(np.float16))
            values.append(v.reshape(W, A).numpy().copy())
            alive.append((sim.alive.cpu().numpy() & policy_slots).copy())
            sim.step(inverse_cdf_sample(logits, th.rand(W * A, generator=gen)).reshape(W, A).to(th.int32))
            task_r.append(sum(sim.reward_terms[k].cpu().numpy() for k in TASK_TERMS))
            if bool(sim.world_done.all()):
                break
    alive = np.stack(alive)
    task_r = np.where(alive, np.stack(task_r), 0.0)
    returns = np.zeros_like(task_r)
    running = np.zeros(task_r.shape[1:])
    for t in range(task_r.shape[0] - 1, -1, -1):
        running = task_r[t] + gamma * running
        returns[t] = running
    ever = alive.any(0)
    last = np.where(ever, alive.shape[0] - 1 - np.argmax(alive[::-1], axis=0), -1)
    return dict(obs=np.stack(obs), alive=alive, values=np.stack(values), returns=returns,
                outcome=sim.outcome.cpu().numpy(), ever=ever, last=last)


def fit(runs: list[dict[str, np.ndarray]], epochs: int, seed: int) -> th.nn.Module:
    x = th.as_tensor(np.concatenate([r["obs"][r["alive"]] for r in runs]), dtype=th.float32)
    y = th.as_tensor(np.concatenate([r["returns"][r["alive"]] for r in runs]), dtype=th.float32)
    th.manual_seed(seed)
    net = th.nn.Sequential(th.nn.Linear(x.shape[1], 128), th.nn.Tanh(), th.nn.Linear(128, 128), th.nn.Tanh(),
                           th.nn.Linear(128, 1))
    opt = th.optim.Adam(net.parameters(), lr=1e-3)
    for epoch in range(epochs):
        perm = th.randperm(x.shape[0])
        total = 0.0
        for lo in range(0, x.shape[0], 512):
            idx = perm[lo:lo + 512]
            loss = ((net(x[idx]).squeeze(-1) - y[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss) * idx.numel()
        if epoch in (0, epochs - 1):
            print(f"fit epoch {epoch}: mse {total / x.shape[0]:.4f} over {x.shape[0]} agent-steps")
    return net


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("model")
    parser.add_argument("--tasks", type=int, default=96)
    parser.add_argument("--fit-seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    parser.add_argument("--seed", type=int, default=0, help="the held-out rollout")
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--gamma", type=float, default=0.99)
    args = parser.parse_args()
    th.set_num_threads(1)
    policy = load_model(args.model, "model").policy
    policy.set_training_mode(False)
    net = fit([rollout(policy, args.tasks, s, args.gamma) for s in args.fit_seeds], args.epochs, args.seed)
    r = rollout(policy, args.tasks, args.seed, args.gamma)
    with th.no_grad():
        task_v = net(th.as_tensor(r["obs"], dtype=th.float32)).squeeze(-1).numpy()
    held = r["alive"]
    print(f"held-out mse {float(((task_v - r['returns'])[held] ** 2).mean()):.4f}, "
          f"return variance {float(r['returns'][held].var()):.4f}")
    roots = np.arange(0, task_v.shape[0], 5)
    print("task value (task return) at d decisions before the agent's last decision")
    print("| outcome | agents | " + " | ".join(f"-{d}" for d in DEPTHS) + " |")
    print("|---|---|" + "---|" * len(DEPTHS))
    for kind in (Outcome.GOAL, Outcome.TIMEOUT, Outcome.COLLISION):
        sel = [(w, a) for w, a in zip(*np.nonzero(r["ever"])) if r["outcome"][w, a] == int(kind)]
        cells = []
        for d in DEPTHS:
            ok = [(w, a) for w, a in sel if r["last"][w, a] - d >= 0]
            cells.append(f"{np.mean([task_v[r['last'][w, a] - d, w, a] for w, a in ok]):.2f} "
                         f"({np.mean([r['returns'][r['last'][w, a] - d, w, a] for w, a in ok]):.2f})")
        print(f"| {kind.name.lower()} | {len(sel)} | " + " | ".join(cells) + " |")
    for kind in (Outcome.TIMEOUT, Outcome.COLLISION):
        sel = [(w, a) for w, a in zip(*np.nonzero(r["ever"])) if r["outcome"][w, a] == int(kind)]
        for name, trace in (("critic value", r["values"]), ("task value", task_v)):
            depths = [int(r["last"][w, a]) - select_root(trace[:, w, a], roots, int(r["last"][w, a]))
                      for w, a in sel if select_root(trace[:, w, a], roots, int(r["last"][w, a])) is not None]
            hist = collections.Counter(depths)
            print(f"{kind.name.lower()}, {name}: depth mean {np.mean(depths):.1f}, median {np.median(depths):.0f}; "
                  + ", ".join(f"{d}: {hist[d]}" for d in sorted(hist)))


if __name__ == "__main__":
    main()
