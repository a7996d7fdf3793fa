"""Refit a checkpoint's critic to its own returns (policy evaluation; the actor is untouched).

The anchor's critic is memoryless (``enable_critic_lstm=False``: observation -> Linear ->
MLP -> value) and was last trained during imitation, on returns of rollouts in which the
teacher drove part of the agents. This script drives ``--tasks`` procedural training tasks
per seed of ``--fit-seeds`` with the checkpoint itself under p_train (every agent a POLICY
agent, sampled actions, as in self-play), computes every agent's discounted return under its
own condition (``--gamma``; the task ends at the deadline, so nothing is bootstrapped), and
regresses the critic's parameters on it (Adam, minibatches of 1,024, ``--epochs``). The
actor's parameters are bit-identical afterwards (checked), so every argmax evaluation of the
result equals the input's. It prints the held-out mean squared error (rollout ``--seed``)
before and after and writes the checkpoint atomically.

    python docs/results/critic_refit/refit_critic.py zoo/anchor.zip runs/critic_refit/J16C.zip
"""

from __future__ import annotations

import argparse
import collections
import time

import numpy as np
import torch as th

from cpalgo.checkpoint import save_model_atomic
from cpalgo.common.policy_utils import inverse_cdf_sample, policy_step_logits, zero_states
from cpalgo.counterplay.search import select_root
from cpalgo.evaluate.runner import load_model
from cpalgo.pretrain import _policy_obs
from cpsim.conditions import sample_conditions
from cpsim.config import Controller, Outcome, SimConfig
from cpsim.scenario.procedural import train_pool
from cpsim.simulator import Simulator
from cpsim.state import REWARD_TERMS


def rollout(policy, tasks: int, seed: int, gamma: float, scales: dict[str, float]) -> dict[str, np.ndarray]:
    """One episode of ``tasks`` worlds: observations (T, W, A, D) float16, ``alive`` (T, W, A)
    live POLICY agents, their discounted returns (T, W, A) with the weighted reward terms of
    ``scales`` multiplied, ``outcome`` (W, A) and the last decision ``last`` (W, A)."""
    W, A = tasks, 8
    config = SimConfig()
    sim = Simulator(train_pool(W, seed=seed), num_worlds=W, max_agents=A, config=config, seed=seed)
    sim.reset(scenario_index=np.arange(W),
              conditions=sample_conditions(np.random.default_rng(seed), (W, A)).astype(np.float32))
    gen = th.Generator().manual_seed(seed)
    states = zero_states(policy, W * A, policy.device)
    starts = th.ones(W * A)
    policy_slots = (sim.controllers == int(Controller.POLICY)).cpu().numpy()
    obs, alive, rewards = [], [], []
    with th.no_grad():
        for _ in range(config.episode_steps):
            o = _policy_obs(sim)
            logits, _, states = policy_step_logits(policy, o, states, starts)
            starts = th.zeros_like(starts)
            obs.append(o.reshape(W, A, -1).numpy().astype(np.float16))
            alive.append((sim.alive.cpu().numpy() & policy_slots).copy())
            sim.step(inverse_cdf_sample(logits, th.rand(W * A, generator=gen)).reshape(W, A).to(th.int32))
            reward = sim.reward.cpu().numpy().copy()
            for term, factor in scales.items():
                reward += (factor - 1.0) * sim.reward_terms[f"w_{term}"].cpu().numpy()
            rewards.append(reward)
            if bool(sim.world_done.all()):
                break
    alive = np.stack(alive)
    return dict(obs=np.stack(obs), alive=alive, returns=discounted_returns(np.stack(rewards), alive, gamma),
                outcome=sim.outcome.cpu().numpy(), last=last_decisions(alive))


def discounted_returns(rewards: np.ndarray, alive: np.ndarray, gamma: float) -> np.ndarray:
    """(T, W, A) discounted return from every decision of live agents (0 elsewhere), float32;
    the episode ends at T, so nothing is bootstrapped."""
    rewards = np.where(alive, rewards, 0.0)
    returns = np.zeros_like(rewards)
    running = np.zeros(rewards.shape[1:])
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = rewards[t] + gamma * running
        returns[t] = running
    return returns.astype(np.float32)


def last_decisions(alive: np.ndarray) -> np.ndarray:
    """(W, A) last decision at which each agent was alive (-1: never)."""
    ever = alive.any(0)
    return np.where(ever, alive.shape[0] - 1 - np.argmax(alive[::-1], axis=0), -1)


def critic_parameters(policy) -> list[th.nn.Parameter]:
    """The parameters only the value path uses (memoryless critic: critic, value MLP, head)."""
    if policy.lstm_critic is not None or policy.shared_lstm:
        raise SystemExit("model: this script refits a memoryless critic (enable_critic_lstm=False)")
    return [*policy.critic.parameters(), *policy.mlp_extractor.value_net.parameters(),
            *policy.value_net.parameters()]


def values_of(policy, x: th.Tensor) -> th.Tensor:
    latent = policy.mlp_extractor.forward_critic(policy.critic(policy.extract_features(x)))
    return policy.value_net(latent).squeeze(-1)


def mse(policy, x: np.ndarray, y: np.ndarray) -> float:
    with th.no_grad():
        total = 0.0
        for lo in range(0, x.shape[0], 8192):
            v = values_of(policy, th.as_tensor(x[lo:lo + 8192], dtype=th.float32))
            total += float(((v - th.as_tensor(y[lo:lo + 8192])) ** 2).sum())
    return total / x.shape[0]


def parse_scales(items: list[str]) -> dict[str, float]:
    scales = {}
    for item in items:
        term, _, factor = item.partition("=")
        if term not in REWARD_TERMS or not factor:
            raise SystemExit(f"--scale: expected TERM=F with TERM in {REWARD_TERMS}, got {item!r}")
        scales[term] = float(factor)
    return scales


def report_roots(policy, held: dict[str, np.ndarray], label: str) -> None:
    """Mean value before the last decision of timeouts and goals, and the value rule's depths
    (roots every 5 decisions, window 5-60, rho 0.5) for the held-out failures."""
    T, W, A, D = held["obs"].shape
    with th.no_grad():
        values = np.concatenate([
            values_of(policy, th.as_tensor(held["obs"][t], dtype=th.float32).reshape(W * A, D)).reshape(1, W, A).numpy()
            for t in range(T)])
    roots = np.arange(0, T, 5)
    ever = held["alive"].any(0)
    for kind in (Outcome.GOAL, Outcome.TIMEOUT, Outcome.COLLISION):
        sel = [(w, a) for w, a in zip(*np.nonzero(ever)) if held["outcome"][w, a] == int(kind)]
        trace = " ".join(f"{np.mean([values[held['last'][w, a] - d, w, a] for w, a in sel if held['last'][w, a] >= d]):.2f}"
                         for d in (60, 40, 20, 10, 5, 0))
        line = f"{label}, {kind.name.lower()} ({len(sel)}): value at 60/40/20/10/5/0 back {trace}"
        if kind != Outcome.GOAL:
            depths = [int(held["last"][w, a]) - r for w, a in sel
                      if (r := select_root(values[:, w, a], roots, int(held["last"][w, a]))) is not None]
            hist = collections.Counter(depths)
            line += (f"; value-rule depth mean {np.mean(depths):.1f}, median {np.median(depths):.0f}, "
                     f"<= 10 back {sum(hist[d] for d in hist if d <= 10)}, 60 back {hist[60]}")
        print(line)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("out")
    parser.add_argument("--tasks", type=int, default=96)
    parser.add_argument("--fit-seeds", type=int, nargs="+", default=[101, 102, 103, 104, 105, 106])
    parser.add_argument("--seed", type=int, default=100, help="the held-out rollout")
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--gamma", type=float, default=0.99)
    parser.add_argument("--scale", nargs="*", default=[], metavar="TERM=F",
                        help="fit the return of a reward whose weighted TERM is multiplied by F "
                             "(e.g. lane_center=0.1); the checkpoint then no longer matches the "
                             "simulator's reward: for the offline question only")
    args = parser.parse_args()
    th.set_num_threads(1)
    t0 = time.time()
    model = load_model(args.model, "model")
    policy = model.policy
    policy.set_training_mode(False)
    params = critic_parameters(policy)
    ids = {id(p) for p in params}
    actor_before = {n: p.detach().clone() for n, p in policy.named_parameters() if id(p) not in ids}
    scales = parse_scales(args.scale)
    runs = [rollout(policy, args.tasks, s, args.gamma, scales) for s in args.fit_seeds]
    x = np.concatenate([r["obs"][r["alive"]] for r in runs])
    y = np.concatenate([r["returns"][r["alive"]] for r in runs])
    held = rollout(policy, args.tasks, args.seed, args.gamma, scales)
    hx, hy = held["obs"][held["alive"]], held["returns"][held["alive"]]
    print(f"{x.shape[0]} agent-steps to fit, {hx.shape[0]} held out; return variance {hy.var():.4f}; "
          f"rollouts {time.time() - t0:.0f} s")
    print(f"before: held-out mse {mse(policy, hx, hy):.4f}, fit mse {mse(policy, x, y):.4f}")
    report_roots(policy, held, "before")
    th.manual_seed(args.seed)
    opt = th.optim.Adam(params, lr=args.lr)
    xt, yt = th.as_tensor(x), th.as_tensor(y)
    for epoch in range(args.epochs):
        perm = th.randperm(xt.shape[0])
        for lo in range(0, xt.shape[0], 1024):
            idx = perm[lo:lo + 1024]
            loss = ((values_of(policy, xt[idx].float()) - yt[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        print(f"epoch {epoch}: held-out mse {mse(policy, hx, hy):.4f}, fit mse {mse(policy, x, y):.4f}")
    report_roots(policy, held, "after")
    for n, p in policy.named_parameters():
        if n in actor_before and not th.equal(actor_before[n], p.detach()):
            raise SystemExit(f"actor parameter {n} changed")
    out = save_model_atomic(model, args.out)
    print(f"critic refit: {args.model} -> {out} in {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
