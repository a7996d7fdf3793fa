"""Timeouts of the reactive teacher under p_train (192 procedural training tasks): how far each
timed-out agent drove against the length of its logged route, how far from its goal it ended and
how long it stood still (< 1 m/s). Optional argument: a profile name whose style fields replace
every agent's (task fields kept).

    python docs/results/anchor_failures/timeout_anatomy.py [aggressive]
"""

from __future__ import annotations

import sys

import numpy as np
import torch as th

from cpsim.conditions import PROFILES, STYLE_MASK, sample_conditions
from cpsim.config import Controller, Outcome, SimConfig
from cpsim.expert import make_expert
from cpsim.scenario.procedural import train_pool
from cpsim.simulator import Simulator


def main() -> None:
    th.set_num_threads(1)
    W, A = 192, 8
    scenarios = train_pool(W, seed=0)
    sim = Simulator(scenarios, num_worlds=W, max_agents=A, config=SimConfig(), seed=0)
    cond = sample_conditions(np.random.default_rng(0), (W, A)).astype(np.float32)
    if len(sys.argv) > 1:
        cond[..., STYLE_MASK] = PROFILES[sys.argv[1]][STYLE_MASK]
    sim.reset(scenario_index=np.arange(W), conditions=cond)
    expert = make_expert("reactive", sim)
    policy = (sim.controllers == int(Controller.POLICY)).cpu().numpy()
    xy, alive = [], []
    for _ in range(sim.config.episode_steps):
        xy.append(sim.xy.cpu().numpy().copy())
        alive.append(sim.alive.cpu().numpy().copy())
        sim.step(expert.actions())
        if bool(sim.world_done.all()):
            break
    xy, alive = np.stack(xy), np.stack(alive)
    outcome = sim.outcome.cpu().numpy()
    index = sim.agent_index.cpu().numpy()
    ever = alive.any(0) & policy
    rows = []
    for w, a in zip(*np.nonzero(ever & (outcome == int(Outcome.TIMEOUT)))):
        scenario, i = scenarios[w], index[w, a]
        log = scenario.log_xy[i][scenario.log_valid[i]]
        speed = np.linalg.norm(np.diff(xy[:, w, a], axis=0), axis=-1) / 0.1
        live = alive[1:, w, a]
        rows.append((np.linalg.norm(np.diff(log, axis=0), axis=-1).sum(), speed[live].sum() * 0.1,
                     np.linalg.norm(xy[-1, w, a] - scenario.goal_xy[i][:2]), np.mean(speed[live] < 1.0), cond[w, a, 0]))
    r = np.array(rows)
    q = [25, 50, 75]
    print(f"timeouts {len(r)} of {int(ever.sum())} policy agents")
    print("logged route length (m) quartiles", np.percentile(r[:, 0], q).round(1))
    print("driven length (m) quartiles", np.percentile(r[:, 1], q).round(1))
    print("driven / logged, deciles 1, quartiles, decile 9", np.percentile(r[:, 1] / np.maximum(r[:, 0], 1e-3),
                                                                            [10, 25, 50, 75, 90]).round(2))
    print("distance to goal at the deadline (m) quartiles", np.percentile(r[:, 2], q).round(1),
          "goal radius quartiles", np.percentile(r[:, 4], q).round(1))
    print("share of decisions standing quartiles", np.percentile(r[:, 3], q).round(2),
          f"standing more than 30%: {np.mean(r[:, 3] > 0.3):.0%}")


if __name__ == "__main__":
    main()
