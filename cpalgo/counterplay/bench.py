"""Wall time per generation of CounterPlay vs RecurrentPPO at the same n_steps and n_envs.

    python -m cpalgo.counterplay.bench --worlds 4 --agents 8 --n-steps 91 --generations 3

Both algorithms train on identical :class:`cpsim.SelfPlayVecEnv` copies (procedural training
pool, conditions from p_train). One warm-up generation each is run first (Warp module load,
branch simulator construction); the timed generations follow, alternating, and the median
is reported. With ``--anchor`` the CounterPlay
run starts from a saved RecurrentPPO / CounterPlay checkpoint (its policy weights), which
is where searches find teachers; a fresh policy rarely completes a retry.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.logger import KVWriter, Logger

__all__ = ["run_benchmark", "main"]


class _MemoryWriter(KVWriter):
    """Keeps every dumped row (one per generation)."""

    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, Any], step: int = 0) -> None:
        self.rows.append(dict(key_values))

    def close(self) -> None:
        pass


def _attach_memory_logger(model: Any) -> _MemoryWriter:
    writer = _MemoryWriter()
    model.set_logger(Logger(folder=None, output_formats=[writer]))
    return writer


def _instrument(model: Any) -> dict[str, list[float]]:
    """Wrap ``collect_rollouts`` and ``train`` of this instance to record their CPU seconds."""
    times: dict[str, list[float]] = {"collect": [], "train": []}
    collect, train = model.collect_rollouts, model.train

    def timed_collect(*args: Any, **kwargs: Any) -> bool:
        start = time.process_time()
        out = collect(*args, **kwargs)
        times["collect"].append(time.process_time() - start)
        return out

    def timed_train() -> None:
        start = time.process_time()
        train()
        times["train"].append(time.process_time() - start)

    model.collect_rollouts, model.train = timed_collect, timed_train
    return times


def _one_generation(model: Any, n_envs: int, n_steps: int) -> tuple[float, float]:
    """(wall seconds, process CPU seconds) of one generation. CPU time is the steadier
    number on a shared machine: with one torch thread and Warp's serial CPU launches the
    process does not run in parallel with itself."""
    wall, cpu = time.perf_counter(), time.process_time()
    model.learn(n_steps * n_envs, reset_num_timesteps=False)
    return time.perf_counter() - wall, time.process_time() - cpu


def run_benchmark(worlds: int = 4, agents: int = 8, n_steps: int = 91, generations: int = 3,
                  branch_cap: float = 0.5, anchor: str | None = None, seed: int = 0,
                  hidden: int = 64, threads: int = 1) -> dict[str, Any]:
    """Time both algorithms; returns a JSON-able summary (median seconds per generation,
    branch share, searches / teachers per generation).

    Generations alternate between the two algorithms (PPO, CounterPlay, PPO, ...) so that
    load from other processes on a shared machine hits both alike.
    """
    from sb3_contrib import RecurrentPPO

    from cpalgo.counterplay.algorithm import CounterPlay
    from cpalgo.counterplay.search import ADMISSION_VERDICTS
    from cpsim import SelfPlayVecEnv

    th.set_num_threads(threads)
    policy_kwargs: dict[str, Any] = dict(lstm_hidden_size=hidden, net_arch=[hidden])
    if anchor is not None:  # build the anchor's own network so its weights load exactly
        from stable_baselines3.common.save_util import load_from_zip_file

        data, _, _ = load_from_zip_file(anchor, device="cpu", load_data=True)
        policy_kwargs = dict(data.get("policy_kwargs") or {})
    common = dict(n_steps=n_steps, batch_size=n_steps * 8, n_epochs=2, seed=seed, device="cpu",
                  policy_kwargs=policy_kwargs)
    env_ppo = SelfPlayVecEnv(num_worlds=worlds, max_agents=agents, seed=seed)
    ppo = RecurrentPPO("MlpLstmPolicy", env_ppo, **common)
    env_cp = SelfPlayVecEnv(num_worlds=worlds, max_agents=agents, seed=seed)
    cp = CounterPlay("MlpLstmPolicy", env_cp, branch_cap=branch_cap, **common)
    if anchor is not None:
        ppo.set_parameters(anchor, exact_match=True, device="cpu")
        cp.set_parameters(anchor, exact_match=True, device="cpu")
    _attach_memory_logger(ppo)
    writer = _attach_memory_logger(cp)
    n_envs = env_cp.num_envs
    ppo.learn(n_steps * n_envs)  # warm-up generation (module loads, branch simulator build)
    cp.learn(n_steps * n_envs)
    writer.rows.clear()
    parts_ppo, parts_cp = _instrument(ppo), _instrument(cp)
    t_ppo, t_cp, c_ppo, c_cp = [], [], [], []
    for _ in range(generations):
        wall, cpu = _one_generation(ppo, n_envs, n_steps)
        t_ppo.append(wall)
        c_ppo.append(cpu)
        wall, cpu = _one_generation(cp, n_envs, n_steps)
        t_cp.append(wall)
        c_cp.append(cpu)
    rows = writer.rows

    def per_gen(key: str) -> float:
        vals = [float(r[key]) for r in rows if key in r]
        return float(np.mean(vals)) if vals else float("nan")

    return {
        "worlds": worlds, "agents": agents, "n_envs": n_envs, "n_steps": n_steps,
        "generations": generations, "branch_cap": branch_cap, "anchor": anchor, "torch_threads": threads,
        "recurrent_ppo_s_per_generation": float(np.median(t_ppo)),
        "counterplay_s_per_generation": float(np.median(t_cp)),
        "recurrent_ppo_s_all": t_ppo,
        "counterplay_s_all": t_cp,
        "recurrent_ppo_cpu_s_per_generation": float(np.median(c_ppo)),
        "counterplay_cpu_s_per_generation": float(np.median(c_cp)),
        "recurrent_ppo_cpu_s_collect": float(np.median(parts_ppo["collect"])),
        "recurrent_ppo_cpu_s_train": float(np.median(parts_ppo["train"])),
        "counterplay_cpu_s_collect_and_search": float(np.median(parts_cp["collect"])),
        "counterplay_cpu_s_train": float(np.median(parts_cp["train"])),
        "counterplay_cpu_s_search": per_gen("counterplay/search_cpu_s"),
        "slowdown_wall": float(np.median(t_cp) / np.median(t_ppo)),
        "slowdown_cpu": float(np.median(c_cp) / np.median(c_ppo)),
        "branch_share": per_gen("counterplay/branch_share"),
        "failures_per_generation": per_gen("counterplay/failures"),
        "searches_per_generation": per_gen("counterplay/searches"),
        "admissible_per_generation": per_gen("counterplay/admissible"),
        "teachers_per_generation": per_gen("counterplay/verified_teachers"),
        # which filter each retry failed (search.admission_verdict), per generation
        "retry_verdicts_per_generation": {v: per_gen(f"counterplay/retries_{v}") for v in ADMISSION_VERDICTS},
        "budget": cp.budget.as_dict(),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m cpalgo.counterplay.bench", description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=4)
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--n-steps", type=int, default=91)
    parser.add_argument("--generations", type=int, default=3)
    parser.add_argument("--branch-cap", type=float, default=0.5)
    parser.add_argument("--anchor", default=None, help="checkpoint .zip whose policy weights CounterPlay starts from")
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    for name in ("worlds", "agents", "n_steps", "generations", "hidden", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1")
    if not args.branch_cap > 0:
        parser.error("--branch-cap must be > 0")
    result = run_benchmark(args.worlds, args.agents, args.n_steps, args.generations, args.branch_cap,
                           args.anchor, args.seed, args.hidden, args.threads)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
