"""Action entropy, comfort violations and hard brakes of drivers under p_train.

Each argument (a checkpoint ``.zip``, sampled actions by the inverse CDF, or a ``cpsim.expert``
teacher name) drives 96 procedural training tasks (seed 0, p_train conditions, every agent a
POLICY agent). Prints, over live POLICY agent-steps: the mean entropy of the action
distribution and its largest probability (checkpoints), comfort violations per step, the share
of hard-brake actions (longitudinal jerk -15 m/s^3) and the outcomes.

    python docs/results/temperature/sampling_stats.py reactive-v6 zoo/anchor.zip runs/temperature/J16_T05.zip
"""

from __future__ import annotations

import sys

import numpy as np
import torch as th

from cpalgo.common.policy_utils import inverse_cdf_sample, policy_step_logits, zero_states
from cpalgo.evaluate.runner import load_model
from cpalgo.pretrain import _policy_obs
from cpsim.conditions import sample_conditions
from cpsim.config import JERK_LAT, Controller, Outcome, SimConfig
from cpsim.expert import make_expert
from cpsim.scenario.procedural import train_pool
from cpsim.simulator import Simulator


def main() -> None:
    th.set_num_threads(1)
    for driver in sys.argv[1:]:
        W, A, seed = 96, 8, 0
        sim = Simulator(train_pool(W, seed=seed), num_worlds=W, max_agents=A, config=SimConfig(), seed=seed)
        sim.reset(scenario_index=np.arange(W),
                  conditions=sample_conditions(np.random.default_rng(seed), (W, A)).astype(np.float32))
        policy_slots = (sim.controllers == int(Controller.POLICY)).cpu().numpy()
        checkpoint = driver.endswith(".zip")
        if checkpoint:
            policy = load_model(driver, "driver").policy
            policy.set_training_mode(False)
            states = zero_states(policy, W * A, policy.device)
            starts = th.ones(W * A)
            gen = th.Generator().manual_seed(seed)
        else:
            expert = make_expert(driver, sim)
        entropy, p_max, violations, hard, steps = [], [], 0.0, 0, 0
        with th.no_grad():
            for _ in range(sim.config.episode_steps):
                alive = sim.alive.cpu().numpy() & policy_slots
                if checkpoint:
                    logits, _, states = policy_step_logits(policy, _policy_obs(sim), states, starts)
                    starts = th.zeros_like(starts)
                    p = th.softmax(logits, -1)
                    live = alive.reshape(-1)
                    entropy.append((-(p * th.log_softmax(logits, -1)).sum(-1)).numpy()[live])
                    p_max.append(p.max(-1).values.numpy()[live])
                    actions = inverse_cdf_sample(logits, th.rand(W * A, generator=gen)).reshape(W, A).to(th.int32)
                else:
                    actions = expert.actions()
                hard += int(((actions.cpu().numpy() // len(JERK_LAT)) == 0)[alive].sum())
                sim.step(actions)
                violations += float(sim.reward_terms["raw_comfort"].cpu().numpy()[alive].sum())
                steps += int(alive.sum())
                if bool(sim.world_done.all()):
                    break
        outcome = sim.outcome.cpu().numpy()[policy_slots]
        counts = ", ".join(f"{o.name.lower()} {np.mean(outcome == int(o)):.1%}" for o in Outcome if o != Outcome.RUNNING)
        line = f"{driver}: comfort violations / step {violations / steps:.3f}, hard brakes {hard / steps:.1%}"
        if checkpoint:
            e, pm = np.concatenate(entropy), np.concatenate(p_max)
            line += f", entropy {e.mean():.3f} nats, largest probability {pm.mean():.3f}"
        print(f"{line}; {counts}")


if __name__ == "__main__":
    main()
