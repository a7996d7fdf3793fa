"""A critic on the actor's memory: does the LSTM's latent predict the return better?

The shipped anchor's critic is memoryless (``enable_critic_lstm=False``). sb3-contrib's
``shared_lstm=True`` would give the critic the actor's LSTM output instead (detached, so the
actor is untouched). This offline check drives 12 rollouts of 96 procedural training tasks
(seeds 101-112, p_train, sampled actions) with the checkpoint, records the actor LSTM's
output at every decision, fits an MLP of the value head's shape (128-128 tanh, Adam 1e-3,
10 epochs) to each agent's discounted return (gamma 0.99; ``TERM=F`` arguments scale weighted
reward terms, as ``refit_critic.py --scale``), and prints the held-out (seed 100) mean
squared error per epoch, the mean value before the last decision per outcome and the value
rule's depths (roots every 5 decisions, window 5-60, rho 0.5).

    python docs/results/critic_refit/latent_critic.py zoo/anchor.zip
"""

from __future__ import annotations

import collections
import sys
from pathlib import Path

import numpy as np
import torch as th

sys.path.insert(0, str(Path(__file__).resolve().parent))
from refit_critic import discounted_returns, last_decisions, parse_scales  # noqa: E402

from cpalgo.common.policy_utils import inverse_cdf_sample, zero_states  # noqa: E402
from cpalgo.counterplay.search import select_root  # noqa: E402
from cpalgo.evaluate.runner import load_model  # noqa: E402
from cpalgo.pretrain import _policy_obs  # noqa: E402
from cpsim.conditions import sample_conditions  # noqa: E402
from cpsim.config import Controller, Outcome, SimConfig  # noqa: E402
from cpsim.scenario.procedural import train_pool  # noqa: E402
from cpsim.simulator import Simulator  # noqa: E402


def rollout(policy, seed: int, scales: dict[str, float], tasks: int = 96, gamma: float = 0.99) -> dict:
    """Actor LSTM outputs (T, W, A, H), alive (T, W, A), returns (T, W, A), outcome and last."""
    W, A = tasks, 8
    sim = Simulator(train_pool(W, seed=seed), num_worlds=W, max_agents=A, config=SimConfig(), seed=seed)
    sim.reset(scenario_index=np.arange(W),
              conditions=sample_conditions(np.random.default_rng(seed), (W, A)).astype(np.float32))
    gen = th.Generator().manual_seed(seed)
    states = zero_states(policy, W * A, policy.device)
    starts = th.ones(W * A)
    policy_slots = (sim.controllers == int(Controller.POLICY)).cpu().numpy()
    latents, alive, rewards = [], [], []
    with th.no_grad():
        for _ in range(sim.config.episode_steps):
            features = policy.extract_features(_policy_obs(sim))
            latent, pi_state = policy._process_sequence(features, states.pi, starts, policy.lstm_actor)
            states = type(states)(pi_state, states.vf)
            logits = policy.action_net(policy.mlp_extractor.forward_actor(latent))
            starts = th.zeros_like(starts)
            latents.append(latent.reshape(W, A, -1).numpy().copy())
            alive.append((sim.alive.cpu().numpy() & policy_slots).copy())
            sim.step(inverse_cdf_sample(logits, th.rand(W * A, generator=gen)).reshape(W, A).to(th.int32))
            reward = sim.reward.cpu().numpy().copy()
            for term, factor in scales.items():
                reward += (factor - 1.0) * sim.reward_terms[f"w_{term}"].cpu().numpy()
            rewards.append(reward)
            if bool(sim.world_done.all()):
                break
    alive = np.stack(alive)
    return dict(lat=np.stack(latents), alive=alive, ret=discounted_returns(np.stack(rewards), alive, gamma),
                outcome=sim.outcome.cpu().numpy(), last=last_decisions(alive))


def main() -> None:
    th.set_num_threads(1)
    policy = load_model(sys.argv[1], "model").policy
    policy.set_training_mode(False)
    scales = parse_scales(sys.argv[2:])
    runs = [rollout(policy, s, scales) for s in range(101, 113)]
    held = rollout(policy, 100, scales)
    x = th.as_tensor(np.concatenate([r["lat"][r["alive"]] for r in runs]))
    y = th.as_tensor(np.concatenate([r["ret"][r["alive"]] for r in runs]))
    hx = th.as_tensor(held["lat"][held["alive"]])
    hy = th.as_tensor(held["ret"][held["alive"]])
    th.manual_seed(0)
    net = th.nn.Sequential(th.nn.Linear(x.shape[1], 128), th.nn.Tanh(), th.nn.Linear(128, 128), th.nn.Tanh(),
                           th.nn.Linear(128, 1))
    opt = th.optim.Adam(net.parameters(), lr=1e-3)
    print(f"{x.shape[0]} fit, variance {float(hy.var()):.4f}")
    for epoch in range(10):
        perm = th.randperm(x.shape[0])
        for lo in range(0, x.shape[0], 1024):
            idx = perm[lo:lo + 1024]
            loss = ((net(x[idx]).squeeze(-1) - y[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        with th.no_grad():
            print(f"epoch {epoch}: held-out mse {float(((net(hx).squeeze(-1) - hy) ** 2).mean()):.4f}")
    T = held["lat"].shape[0]
    with th.no_grad():
        values = net(th.as_tensor(held["lat"])).squeeze(-1).numpy()
    roots = np.arange(0, T, 5)
    ever = held["alive"].any(0)
    last = held["last"]
    for kind in (Outcome.GOAL, Outcome.TIMEOUT, Outcome.COLLISION):
        sel = [(w, a) for w, a in zip(*np.nonzero(ever)) if held["outcome"][w, a] == int(kind)]
        trace = " ".join(f"{np.mean([values[last[w, a] - d, w, a] for w, a in sel if last[w, a] >= d]):.2f}"
                         for d in (60, 40, 20, 10, 5, 0))
        line = f"{kind.name.lower()} ({len(sel)}): value at 60/40/20/10/5/0 back {trace}"
        if kind != Outcome.GOAL:
            depths = [int(last[w, a]) - r for w, a in sel
                      if (r := select_root(values[:, w, a], roots, int(last[w, a]))) is not None]
            hist = collections.Counter(depths)
            line += (f"; depth mean {np.mean(depths):.1f}, median {np.median(depths):.0f}, "
                     f"<=10 back {sum(hist[d] for d in hist if d <= 10)}, 60 back {hist[60]}, "
                     f"hist {sorted(hist.items())}")
        print(line)


if __name__ == "__main__":
    main()
