"""Learn throughput: sb3-contrib's RecurrentPPO vs the fused policy vs CounterPlay.

    python -m cpalgo.bench --worlds 16 --agents 8 --n-steps 64 --generations 3

Four learners train on identical :class:`cpsim.SelfPlayVecEnv` copies (procedural training
pool, conditions from p_train) with the same network (the shipped jerk anchor ``anchor_imitation.zip``'s by default) and
the same hyperparameters:

* ``stock``: ``RecurrentPPO`` with sb3-contrib's ``MlpLstmPolicy`` (stepping LSTM);
* ``fused``: ``RecurrentPPO`` with :class:`cpalgo.policies.MlpLstmPolicy`;
* ``ppo``: ``CounterPlay(counterfactual=False)``: fused policy, inactive slots skipped in
  rollout inference and in every minibatch (what PPO-Continue runs);
* ``counterplay``: ``CounterPlay`` with every feature on (roots, searches, verification,
  distillation).

One warm-up generation each comes first (Warp module load, branch simulator build); the
timed generations then alternate between the learners, so load from other processes on a
shared machine hits all of them alike, and medians are reported. Throughput is given in
slot-steps/s (SB3's ``num_timesteps``: every VecEnv index per step) and in active
transitions/s (slots holding a live policy agent), with a per-phase breakdown of each
generation: rollout, search, train.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np
import torch as th

from cpalgo.counterplay.bench import _attach_memory_logger

__all__ = ["run_learn_benchmark", "run_recipe_benchmark", "flops_per_transition", "main", "LEARNERS"]

LEARNERS = ("stock", "fused", "ppo", "counterplay")


def _phase_timer(model: Any) -> dict[str, list[float]]:
    """Wrap ``collect_rollouts`` and ``train`` of one instance to record wall seconds.

    CounterPlay's searches run inside ``collect_rollouts``; their share is read from the
    generation's ``counterplay/search_wall_s`` log entry and taken out of the rollout.
    """
    times: dict[str, list[float]] = {"collect": [], "train": []}
    collect, train = model.collect_rollouts, model.train

    def timed_collect(*args: Any, **kwargs: Any) -> bool:
        start = time.perf_counter()
        out = collect(*args, **kwargs)
        times["collect"].append(time.perf_counter() - start)
        return out

    def timed_train() -> None:
        start = time.perf_counter()
        train()
        times["train"].append(time.perf_counter() - start)

    model.collect_rollouts, model.train = timed_collect, timed_train
    return times


def _anchor_path(anchor: str | None) -> str:
    """``anchor``, or the shipped jerk anchor whose network the benchmarks use by default."""
    from cpalgo.recipes import shipped_path

    return anchor or str(shipped_path("anchor_imitation.zip"))


def _anchor_network(anchor: str | None) -> dict[str, Any]:
    path = _anchor_path(anchor)
    from stable_baselines3.common.save_util import load_from_zip_file

    data, _, _ = load_from_zip_file(path, device="cpu", load_data=True)
    return dict(data.get("policy_kwargs") or {})


def _make(name: str, env: Any, common: dict[str, Any]) -> Any:
    from sb3_contrib import RecurrentPPO

    from cpalgo.counterplay.algorithm import CounterPlay
    from cpalgo.policies import MlpLstmPolicy

    if name == "stock":
        return RecurrentPPO("MlpLstmPolicy", env, **common)
    if name == "fused":
        return RecurrentPPO(MlpLstmPolicy, env, **common)
    if name == "ppo":
        return CounterPlay("MlpLstmPolicy", env, counterfactual=False, **common)
    return CounterPlay("MlpLstmPolicy", env, **common)


def run_learn_benchmark(worlds: int = 16, agents: int = 8, n_steps: int = 64, generations: int = 3,
                        batch_size: int = 4096, n_epochs: int = 3, anchor: str | None = None,
                        learners: tuple[str, ...] = LEARNERS, seed: int = 0, threads: int | None = None,
                        init_weights: bool = True, device: str = "cpu") -> dict[str, Any]:
    """Time the learners; returns a JSON-able summary (see the module docstring).

    Args:
        worlds, agents: ``SelfPlayVecEnv`` size (slots = worlds x agents).
        n_steps, batch_size, n_epochs: PPO settings shared by every learner.
        anchor: checkpoint whose network (and, with ``init_weights``, weights) every
            learner uses; default the teacher-imitation anchor (``zoo/anchor_imitation.zip``).
        threads: torch intra-op threads (None: leave torch's choice).
        device: ``"cpu"`` or ``"cuda[:n]"``: simulator, policy, rollout buffer and branch
            search of every learner on that device.
    """
    from cpsim import SelfPlayVecEnv

    if device != "cpu" and not str(device).startswith("cuda"):
        raise ValueError(f"device: expected 'cpu' or 'cuda[:n]', got {device!r}")
    if str(device).startswith("cuda") and not th.cuda.is_available():
        raise ValueError(f"device: {device!r} requested but torch sees no CUDA device")

    unknown = [n for n in learners if n not in LEARNERS]
    if unknown:
        raise ValueError(f"learners: unknown {unknown}; accepted: {list(LEARNERS)}")
    if threads is not None:
        th.set_num_threads(int(threads))
    policy_kwargs = _anchor_network(anchor)
    common = dict(n_steps=n_steps, batch_size=batch_size, n_epochs=n_epochs, seed=seed, device=device,
                  policy_kwargs=policy_kwargs)
    models: dict[str, Any] = {}
    for name in learners:
        env = SelfPlayVecEnv(num_worlds=worlds, max_agents=agents, seed=seed, device=device)
        model = _make(name, env, common)
        if init_weights:
            model.set_parameters(_anchor_path(anchor), exact_match=False, device=device)
        models[name] = model
    writers = {name: _attach_memory_logger(m) for name, m in models.items()}
    n_envs = worlds * agents

    def one_generation(name: str, model: Any, reset: bool) -> None:
        # SB3 learners count slot-steps, CounterPlay-based ones B_post: ask each for exactly
        # one rollout + one update
        model.learn(n_steps * n_envs if name in ("stock", "fused") else 1, reset_num_timesteps=reset)

    for name, model in models.items():
        one_generation(name, model, True)  # warm-up generation
    for w in writers.values():
        w.rows.clear()
    phases = {name: _phase_timer(m) for name, m in models.items()}
    walls: dict[str, list[float]] = {name: [] for name in models}
    active: dict[str, list[int]] = {name: [] for name in models}
    for _ in range(generations):
        for name, model in models.items():
            buffer = model.rollout_buffer
            start = time.perf_counter()
            one_generation(name, model, False)
            walls[name].append(time.perf_counter() - start)
            act = getattr(buffer, "active", None)
            env = model.get_env()
            # the plain RecurrentPPO buffer stores no activity: count live slots from the env's record
            active[name].append(int(np.count_nonzero(act)) if act is not None else -1)
            del env

    out: dict[str, Any] = {
        "worlds": worlds, "agents": agents, "slots": n_envs, "n_steps": n_steps, "batch_size": batch_size,
        "n_epochs": n_epochs, "generations": generations, "torch_threads": th.get_num_threads(), "device": device,
        "network": repr(policy_kwargs), "learners": {},
    }
    slot_steps = n_steps * n_envs
    ref_active = next((int(np.median(v)) for v in active.values() if v and v[0] >= 0), -1)
    for name in models:
        wall = float(np.median(walls[name]))
        rows = writers[name].rows
        search = float(np.median([r.get("counterplay/search_wall_s", 0.0) for r in rows])) if rows else 0.0
        collect = float(np.median(phases[name]["collect"]))
        entry = {
            "s_per_generation": wall,
            "slot_steps_per_s": slot_steps / wall,
            "active_transitions_per_s": ref_active / wall if ref_active > 0 else float("nan"),
            "rollout_s": collect - search,
            "search_s": search,
            "train_s": float(np.median(phases[name]["train"])),
        }
        if name == "counterplay" and rows:
            for key in ("searches", "admissible", "verified_teachers", "branch_share"):
                entry[key] = float(np.mean([r.get(f"counterplay/{key}", 0.0) for r in rows]))
        out["learners"][name] = entry
    out["active_fraction"] = ref_active / slot_steps if ref_active > 0 else float("nan")
    if "stock" in models:
        base = out["learners"]["stock"]["s_per_generation"]
        out["speedup_vs_stock"] = {n: base / e["s_per_generation"] for n, e in out["learners"].items()}
    if "fused" in models and "counterplay" in models:
        out["counterplay_wall_over_fused"] = (out["learners"]["counterplay"]["s_per_generation"]
                                              / out["learners"]["fused"]["s_per_generation"])
    if "ppo" in models and "counterplay" in models:
        out["counterplay_wall_over_ppo"] = (out["learners"]["counterplay"]["s_per_generation"]
                                            / out["learners"]["ppo"]["s_per_generation"])
    return out


def _lstm_flops(policy: Any) -> float:
    """Forward FLOPs of one step of every LSTM of ``policy`` (FlopCounterMode does not see
    ``aten.lstm``): 2 x 4 H (I + H) multiply-adds per layer."""
    total = 0.0
    for lstm in (getattr(policy, "lstm_actor", None), getattr(policy, "lstm_critic", None)):
        if lstm is not None:
            inp, hid = lstm.input_size, lstm.hidden_size
            for layer in range(lstm.num_layers):
                total += 2.0 * 4 * hid * ((inp if layer == 0 else hid) + hid)
    return total


def flops_per_transition(policy: Any, obs_dim: int, n: int = 256) -> dict[str, float]:
    """FLOPs of one live transition: ``inference`` (one forward of actor and critic, as in the
    rollout) and ``train`` (forward and backward of ``evaluate_actions``), counted with
    ``torch.utils.flop_counter`` on ``n`` random observations, plus the LSTMs analytically
    (backward = 2 x forward)."""
    from sb3_contrib.common.recurrent.type_aliases import RNNStates
    from torch.utils.flop_counter import FlopCounterMode

    device = policy.device
    obs = th.rand((n, obs_dim), device=device) * 2 - 1
    lstm = policy.lstm_actor
    zeros = th.zeros((lstm.num_layers, n, lstm.hidden_size), device=device)
    states = RNNStates((zeros, zeros), (zeros, zeros))
    starts = th.zeros(n, device=device)
    with th.no_grad(), FlopCounterMode(display=False) as counter:
        policy(obs, states, starts)
    inference = counter.get_total_flops() / n + _lstm_flops(policy)
    with FlopCounterMode(display=False) as counter:
        values, log_prob, entropy = policy.evaluate_actions(obs, th.zeros(n, device=device), states, starts)
        (values.sum() + log_prob.sum() + entropy.sum()).backward()
    policy.zero_grad(set_to_none=True)
    train = counter.get_total_flops() / n + 3 * _lstm_flops(policy)
    return {"inference": float(inference), "train": float(train)}


def run_recipe_benchmark(recipes: tuple[str, ...], generations: int = 3, seed: int = 0,
                         threads: int | None = None, device: str = "cpu") -> dict[str, Any]:
    """Time whole anchor recipes (zoo YAML) end to end, from scratch, as ``counterplay
    train-anchor`` runs them: each recipe's env (its worlds, slots, dynamics), network and
    PPO settings on the fast learner (``CounterPlay(counterfactual=False)``).

    One warm-up generation each, then ``generations`` timed generations alternating between
    the recipes (load from other processes hits all alike); medians. Per recipe: live
    transitions per generation, rollout and train seconds, live transitions/s end to end,
    FLOPs per live transition (inference once, training ``n_epochs`` times) and the FLOP
    rate of ``train``.
    """
    from stable_baselines3.common.vec_env import VecMonitor

    from cpalgo.counterplay.algorithm import CounterPlay
    from cpalgo.recipes import load_recipe
    from cpsim import SelfPlayVecEnv

    if threads is not None:
        th.set_num_threads(int(threads))
    models: dict[str, Any] = {}
    for path in recipes:
        recipe = load_recipe(path)
        kwargs = {k: v for k, v in recipe.env_kwargs.items() if k != "seed"}
        env = VecMonitor(SelfPlayVecEnv(num_worlds=recipe.num_worlds, seed=seed, device=device, **kwargs))
        algo = {k: v for k, v in recipe.algo_kwargs.items() if k != "schedule_timesteps"}
        models[path] = CounterPlay(recipe.policy, env, counterfactual=False, seed=seed, device=device, **algo)
    for model in models.values():
        model.learn(1)  # warm-up: module load, buffers, first allocations
    phases = {name: _phase_timer(m) for name, m in models.items()}
    walls: dict[str, list[float]] = {name: [] for name in models}
    live: dict[str, list[int]] = {name: [] for name in models}
    for _ in range(generations):
        for name, model in models.items():
            before = model.num_timesteps
            start = time.perf_counter()
            model.learn(1, reset_num_timesteps=False)
            walls[name].append(time.perf_counter() - start)
            live[name].append(model.num_timesteps - before)
    out: dict[str, Any] = {"generations": generations, "torch_threads": th.get_num_threads(), "device": device,
                           "recipes": {}}
    for name, model in models.items():
        wall = float(np.median(walls[name]))
        transitions = float(np.median(live[name]))
        train_s = float(np.median(phases[name]["train"]))
        flops = flops_per_transition(model.policy, int(model.observation_space.shape[0]))
        epochs = int(model.n_epochs)
        out["recipes"][name] = {
            "policy": type(model.policy).__name__,
            "parameters": int(sum(p.numel() for p in model.policy.parameters())),
            "slots": int(model.n_envs), "n_steps": int(model.n_steps), "batch_size": int(model.batch_size),
            "n_epochs": epochs, "live_transitions_per_generation": transitions,
            "s_per_generation": wall, "rollout_s": float(np.median(phases[name]["collect"])), "train_s": train_s,
            "live_transitions_per_s": transitions / wall,
            "flops_per_transition": {**flops, "total": flops["inference"] + epochs * flops["train"]},
            "train_gflops_per_s": epochs * flops["train"] * transitions / train_s / 1e9,
        }
    names = list(models)
    if len(names) > 1:
        base = out["recipes"][names[0]]["live_transitions_per_s"]
        out["speedup_vs_first"] = {n: out["recipes"][n]["live_transitions_per_s"] / base for n in names}
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m cpalgo.bench", description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=16)
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--n-steps", type=int, default=64)
    parser.add_argument("--batch-size", type=int, default=4096)
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--generations", type=int, default=3)
    parser.add_argument("--anchor", default=None, help="checkpoint whose network/weights to use (default: shipped anchor)")
    parser.add_argument("--learners", default=",".join(LEARNERS), help=f"comma-separated subset of {','.join(LEARNERS)}")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="also write the JSON summary here")
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:n] (simulator, learners and search)")
    parser.add_argument("--recipes", default=None, metavar="YAML,YAML",
                        help="instead: time these anchor recipes end to end from scratch, each with its own env, "
                             "network and PPO settings (e.g. zoo/anchor.yml,zoo/anchor_selfplay.yml)")
    parser.add_argument("--same-learning", type=int, default=0, metavar="GENERATIONS",
                        help="instead: post-train the anchor with the stock and the fast learner for this many "
                             "generations each and compare held-out outcome rates")
    args = parser.parse_args(argv)
    for name in ("worlds", "agents", "n_steps", "batch_size", "epochs", "generations"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1")
    learners = tuple(x.strip() for x in args.learners.split(",") if x.strip())
    if args.recipes:
        try:
            result = run_recipe_benchmark(tuple(x.strip() for x in args.recipes.split(",") if x.strip()),
                                          args.generations, args.seed, args.threads, args.device)
        except ValueError as exc:
            parser.error(str(exc))
        _emit(json.dumps(result, indent=2), args.out)
        return
    if args.same_learning > 0:
        result = compare_learning(args.same_learning, args.worlds, args.agents, args.n_steps, args.batch_size,
                                  args.epochs, seed=args.seed, anchor=args.anchor)
        _emit(json.dumps(result, indent=2), args.out)
        return
    try:
        result = run_learn_benchmark(args.worlds, args.agents, args.n_steps, args.generations, args.batch_size,
                                     args.epochs, args.anchor, learners, args.seed, args.threads,
                                     device=args.device)
    except ValueError as exc:
        parser.error(str(exc))
    _emit(json.dumps(result, indent=2), args.out)


def _emit(text: str, out: str | None) -> None:
    print(text)
    if out:
        from cpsim.atomic import atomic_path

        with atomic_path(out) as tmp, open(tmp, "w") as fh:
            fh.write(text)



def compare_learning(generations: int = 18, worlds: int = 32, agents: int = 8, n_steps: int = 64,
                     batch_size: int = 4096, n_epochs: int = 3, learning_rate: float = 3e-4, tasks: int = 256,
                     seed: int = 0, anchor: str | None = None) -> dict[str, Any]:
    """"Same learning": the stock and the fast learner post-train the shipped anchor for the
    same number of generations (same rollouts: ``generations x n_steps x slots`` slot-steps,
    same seed), then both are measured on the same held-out tasks.

    Learners: ``stock`` (``RecurrentPPO`` with sb3-contrib's policy) and ``ppo`` (the fast
    path: ``CounterPlay(counterfactual=False)``, fused LSTM, live slots only). Returns goal /
    collision / off-road / timeout rates under the normal condition (argmax actions,
    evaluation goal criterion), the anchor's included, and each learner's wall time.
    """
    from cpalgo.anchor.outcomes import selfplay_outcomes
    from cpalgo.cli import _held_out
    from cpsim import SelfPlayVecEnv

    path = _anchor_path(anchor)
    common = dict(n_steps=n_steps, batch_size=batch_size, n_epochs=n_epochs, seed=seed, device="cpu",
                  learning_rate=learning_rate, policy_kwargs=_anchor_network(anchor))
    held_out = _held_out(tasks)
    out: dict[str, Any] = {"generations": generations, "slot_steps": generations * n_steps * worlds * agents,
                           "tasks": tasks, "seed": seed, "learning_rate": learning_rate, "rates": {}, "wall_s": {}}
    for name in ("stock", "ppo"):
        env = SelfPlayVecEnv(num_worlds=worlds, max_agents=agents, seed=seed)
        model = _make(name, env, common)
        model.set_parameters(path, exact_match=False, device="cpu")
        if name == "stock":
            out["rates"]["anchor"] = selfplay_outcomes(model, held_out).as_dict()
        start = time.perf_counter()
        for _ in range(generations):
            # one generation per call: rollouts of the same size whatever learn counts
            model.learn(n_steps * env.num_envs if name == "stock" else 1, reset_num_timesteps=False)
        out["wall_s"][name] = time.perf_counter() - start
        out["rates"][name] = selfplay_outcomes(model, held_out).as_dict()
    return out


if __name__ == "__main__":
    main()
