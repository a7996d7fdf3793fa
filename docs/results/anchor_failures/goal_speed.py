"""Teacher self-play under p_train conditions and the training goal test (each agent's own goal
radius and speed): outcome rates, and how many timeouts came within their goal radius too fast.

    python docs/results/anchor_failures/goal_speed.py reactive      # teacher version 3
    python docs/results/anchor_failures/goal_speed.py reactive-v2   # without the goal speed limit
    python docs/results/anchor_failures/goal_speed.py zoo/anchor.zip  # a checkpoint (argmax actions)

192 procedural training tasks (cpsim.scenario.procedural.train_pool(192, seed=0)), 8 slots,
conditions from p_train (seed 0). About 40 s on one core.
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from cpsim.conditions import FIELD_INDEX, sample_conditions
from cpsim.config import Controller, Outcome, SimConfig
from cpsim.expert import make_expert
from cpsim.scenario.procedural import train_pool
from cpsim.simulator import Simulator


def main(teacher: str = "reactive", n: int = 192) -> None:
    torch.set_num_threads(1)
    sim = Simulator(train_pool(n, seed=0), num_worlds=n, max_agents=8, config=SimConfig(), seed=0)
    W, A = sim.num_worlds, sim.max_agents
    cond = sample_conditions(np.random.default_rng(0), (W, A))
    sim.reset(scenario_index=np.arange(W), conditions=cond)
    policy = ((sim.controllers == int(Controller.POLICY)) & sim.alive).cpu().numpy()
    if teacher.endswith(".zip"):
        from cpalgo.evaluate.runner import load_model

        model, state = load_model(teacher, "teacher"), None
        starts = np.ones(W * A, bool)

        def actions() -> torch.Tensor:
            nonlocal state
            obs = sim.obs.reshape(W * A, -1).cpu().numpy().copy()
            obs[~sim.policy_mask.reshape(-1).cpu().numpy()] = 0.0
            act, state = model.predict(obs, state=state, episode_start=starts, deterministic=True)
            starts[:] = False
            return torch.as_tensor(np.asarray(act).reshape(W, A), dtype=torch.int32)
    else:
        actions = make_expert(teacher, sim).actions
    radius, goal_speed = cond[..., FIELD_INDEX["goal_radius"]], cond[..., FIELD_INDEX["goal_speed"]]
    inside_fast = np.zeros((W, A), bool)
    for _ in range(sim.config.episode_steps):
        sim.step(actions())
        dist = np.linalg.norm(sim.xy.cpu().numpy() - sim.goal.cpu().numpy(), axis=-1)
        inside_fast |= (dist <= radius) & (sim.speed.cpu().numpy() > goal_speed) & sim.alive.cpu().numpy()
        if bool(sim.world_done.all()):
            break
    out = sim.outcome.cpu().numpy()
    for o in Outcome:
        share = float(np.mean(out[policy] == int(o)))
        if share:
            print(f"{o.name.lower()}: {share:.3f}")
    timeout = policy & ((out == int(Outcome.TIMEOUT)) | (out == int(Outcome.RUNNING)))
    print(f"{int(timeout.sum())} timeouts of {int(policy.sum())} agents, "
          f"{int((timeout & inside_fast).sum())} of them inside their goal radius above their goal speed")


if __name__ == "__main__":
    main(*sys.argv[1:2])
