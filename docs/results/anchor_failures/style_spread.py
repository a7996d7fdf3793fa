"""How far the styles of one driver drift apart from the same state: the imitation teacher or a
checkpoint drives 192 procedural training tasks under p_train conditions for ``--t0`` decisions;
the worlds are snapshotted, and every POLICY agent is re-driven from there twice, with the
style fields of the cautious and of the aggressive profile (task fields kept), all agents of the
world under the same swap. Reported: per agent alive at the root, the largest distance between
its two positions over the next 10 and 30 decisions while it drives in both copies (argmax
actions for a checkpoint).

    python docs/results/anchor_failures/style_spread.py reactive
    python docs/results/anchor_failures/style_spread.py zoo/anchor.zip

About 1 min on one core.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from cpsim.conditions import PROFILES, STYLE_MASK, sample_conditions
from cpsim.config import Controller, SimConfig
from cpsim.expert import make_expert
from cpsim.scenario.procedural import train_pool
from cpsim.simulator import Simulator


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("driver", help="a cpsim.expert name or a checkpoint .zip")
    parser.add_argument("--t0", type=int, default=30)
    parser.add_argument("--tasks", type=int, default=192)
    args = parser.parse_args()
    torch.set_num_threads(1)
    n = args.tasks
    sim = Simulator(train_pool(n, seed=0), num_worlds=n, max_agents=8, config=SimConfig(), seed=0)
    W, A = sim.num_worlds, sim.max_agents
    cond = sample_conditions(np.random.default_rng(0), (W, A))
    sim.reset(scenario_index=np.arange(W), conditions=cond)
    policy = ((sim.controllers == int(Controller.POLICY)) & sim.alive).cpu().numpy()
    if args.driver.endswith(".zip"):
        from cpalgo.evaluate.runner import load_model

        model = load_model(args.driver, "driver")
        memory = {"state": None, "start": np.ones(W * A, bool)}

        def actions() -> torch.Tensor:
            obs = sim.obs.reshape(W * A, -1).cpu().numpy().copy()
            obs[~sim.policy_mask.reshape(-1).cpu().numpy()] = 0.0
            act, memory["state"] = model.predict(obs, state=memory["state"], episode_start=memory["start"],
                                                 deterministic=True)
            memory["start"] = np.zeros(W * A, bool)
            return torch.as_tensor(np.asarray(act).reshape(W, A), dtype=torch.int32)
    else:
        memory = {"state": None}
        actions = make_expert(args.driver, sim).actions
    for _ in range(args.t0):
        sim.step(actions())
    root = sim.snapshot(np.arange(W))
    alive = sim.alive.cpu().numpy() & policy
    root_memory = memory["state"]
    tracks, driving = {}, {}
    for style in ("cautious", "aggressive"):
        sim.restore(root, np.arange(W))
        memory["state"] = root_memory
        styled = cond.copy()
        styled[..., STYLE_MASK] = PROFILES[style][STYLE_MASK]
        sim.set_conditions(styled)
        xy, on = [], []
        for _ in range(30):
            sim.step(actions())
            xy.append(sim.xy.cpu().numpy().copy())
            on.append(sim.alive.cpu().numpy().copy())
        tracks[style], driving[style] = np.stack(xy), np.stack(on)  # (30, W, A, 2), (30, W, A)
    # an agent removed in one copy (goal, collision, off-road) stops there: compare the steps it
    # drives in both copies
    both = np.cumprod(driving["cautious"] & driving["aggressive"], axis=0).astype(bool)
    gap = np.where(both, np.linalg.norm(tracks["cautious"] - tracks["aggressive"], axis=-1), 0.0)
    for h in (10, 30):
        g = gap[:h].max(0)[alive]
        print(f"{args.driver}: {alive.sum()} agents, cautious vs aggressive within {h} decisions: median "
              f"{np.median(g):.2f} m, 75th percentile {np.percentile(g, 75):.2f} m, share > 1 m {np.mean(g > 1):.0%}")


if __name__ == "__main__":
    main()
