"""Front-end throughput: ``python -m cpsim.envs.bench``.

Measures, on one procedural pool and one simulator size:

* raw ``Simulator.step`` agent-steps/s (no copies),
* ``SelfPlayVecEnv.step`` env-steps/s (one env-step = one agent slot; observation,
  reward and info copies included), counting all slots and active slots only,
* ``PPO.learn`` env-steps/s on the SelfPlayVecEnv (rollout + update),
* ``DriveEnv.step`` steps/s (one ego, co-players on IDM) and frame rendering time.

Keep runs short on shared machines (``--steps``, ``--learn-steps``).
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np


def _rate(n: float, seconds: float) -> float:
    return n / max(seconds, 1e-9)


def run(num_worlds: int = 64, max_agents: int = 32, steps: int = 200, learn_steps: int = 8192,
        num_scenarios: int = 8, device: str = "cpu", seed: int = 0) -> dict[str, Any]:
    from cpsim.envs.selfplay import SelfPlayVecEnv

    t0 = time.perf_counter()
    env = SelfPlayVecEnv(None, num_worlds=num_worlds, max_agents=max_agents, num_scenarios=num_scenarios,
                         device=device, seed=seed)
    build_s = time.perf_counter() - t0
    sim = env.sim
    rng = np.random.default_rng(seed)
    n = env.num_envs
    out: dict[str, Any] = {"num_worlds": num_worlds, "max_agents": max_agents, "num_envs": n,
                           "obs_size": int(env.observation_space.shape[0]), "device": sim.device,
                           "build_s": round(build_s, 2)}

    # raw simulator: (W, A) actions, no copies, worlds restarted with reset() when done
    actions = rng.integers(0, env.action_space.n, size=(num_worlds, max_agents))
    sim.reset()
    for _ in range(5):
        sim.step(actions)
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.step(actions)
        done = sim.world_done.cpu().numpy()
        if done.any():
            sim.reset(worlds=np.flatnonzero(done))
    out["sim_agent_steps_per_s"] = _rate(steps * n, time.perf_counter() - t0)

    # through the VecEnv: copies, masking, infos, auto-reset
    env.reset()
    flat = actions.reshape(-1)
    active = 0
    for _ in range(5):
        env.step(flat)
    t0 = time.perf_counter()
    for _ in range(steps):
        env.step(flat)
        active += int(env.active_mask().sum())
    dt = time.perf_counter() - t0
    out["vecenv_env_steps_per_s"] = _rate(steps * n, dt)
    out["vecenv_active_steps_per_s"] = _rate(active, dt)
    out["active_fraction"] = active / (steps * n)

    if learn_steps > 0:
        from stable_baselines3 import PPO

        n_steps = max(8, learn_steps // (2 * n))  # two rollouts, at least 8 steps each
        model = PPO("MlpPolicy", env, n_steps=n_steps, batch_size=min(4096, n * n_steps), n_epochs=1,
                    seed=seed, device="cpu")
        t0 = time.perf_counter()
        model.learn(total_timesteps=2 * n * n_steps)
        out["ppo_learn_env_steps_per_s"] = _rate(model.num_timesteps, time.perf_counter() - t0)
        out["ppo_n_steps"] = n_steps
    env.close()

    from cpsim.envs.drive import DriveEnv

    d = DriveEnv(None, num_scenarios=num_scenarios, regime="idm", seed=seed, max_agents=max_agents,
                 render_mode="rgb_array", device=device)
    d.reset(seed=seed)
    t0 = time.perf_counter()
    k = 0
    while k < steps:
        _, _, te, tr, _ = d.step(7)
        k += 1
        if te or tr:
            d.reset()
    out["drive_env_steps_per_s"] = _rate(k, time.perf_counter() - t0)
    d.render()
    t0 = time.perf_counter()
    for _ in range(20):
        d.render()
    out["render_ms_per_frame"] = 1000 * (time.perf_counter() - t0) / 20
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m cpsim.envs.bench", description=__doc__.splitlines()[0])
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--agents", type=int, default=32)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--learn-steps", type=int, default=8192)
    p.add_argument("--scenarios", type=int, default=8)
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    res = run(a.worlds, a.agents, a.steps, a.learn_steps, a.scenarios, a.device, a.seed)
    print(json.dumps({k: (round(v, 1) if isinstance(v, float) else v) for k, v in res.items()}, indent=1))


if __name__ == "__main__":
    main()
