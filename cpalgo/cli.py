"""The ``counterplay`` command.

Sub-commands::

    counterplay run            post-train the shipped anchor with CounterPlay on procedural
                               scenarios, evaluate before/after, write checkpoint + summary
                               (the README's main job)
    counterplay post-train     the same with every option exposed
    counterplay train-anchor   train the reward-conditioned self-play anchor (RecurrentPPO)
    counterplay outcomes       self-play outcome rates of a checkpoint on held-out tasks
    counterplay pool           generate and summarise a procedural scenario pool
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

from cpalgo.recipes import ZOO_DIR, load_recipe

DEFAULT_ANCHOR = ZOO_DIR / "anchor.zip"
DEFAULT_ANCHOR_CONFIG = ZOO_DIR / "anchor.yml"
DEFAULT_POST_CONFIG = ZOO_DIR / "counterplay.yml"
#: Held-out tasks come from the evaluation seed range (disjoint from training by seed).
HELD_OUT_SEED = 0


def _positive_int(text: str) -> int:
    value = int(float(text))
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


def _non_negative_int(text: str) -> int:
    value = int(float(text))
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def _unit_float(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text}")
    return value


def _set_threads(threads: int | None) -> None:
    import torch

    if threads:
        torch.set_num_threads(threads)


def _make_env(recipe: Any, seed: int, num_worlds: int | None = None, **overrides: Any) -> Any:
    import cpsim

    kwargs = dict(recipe.env_kwargs)
    kwargs.update(overrides)
    kwargs.setdefault("seed", seed)
    from stable_baselines3.common.vec_env import VecMonitor

    # VecMonitor gives SB3 its episode statistics (rollout/ep_rew_mean); attribute access
    # (env.sim, env.obs_layout) passes through the wrapper.
    return VecMonitor(cpsim.SelfPlayVecEnv(num_worlds=num_worlds or recipe.num_worlds, **kwargs))


@functools.lru_cache(maxsize=4)
def _held_out(n: int) -> tuple:
    """The first ``n`` held-out tasks (generated once per process: before and after share them)."""
    from cpsim.scenario import eval_pool

    return tuple(eval_pool(n, seed=HELD_OUT_SEED))


def _outcomes(model: Any, n_tasks: int, max_agents: int, condition: str = "normal") -> Any:
    from cpalgo.selfplay_eval import selfplay_outcomes

    return selfplay_outcomes(model, _held_out(n_tasks), condition=condition, max_agents=max_agents)


# ----------------------------------------------------------------------------- pool
def cmd_pool(args: argparse.Namespace) -> int:
    from cpsim.scenario import FAMILIES, pool

    families = args.families or None
    if families:
        unknown = sorted(set(families) - set(FAMILIES))
        if unknown:
            raise SystemExit(f"--families: unknown {unknown}; accepted: {list(FAMILIES)}")
    t0 = time.perf_counter()
    scenarios = pool(args.n, args.seed, families=families)
    dt = time.perf_counter() - t0
    by_family: dict[str, list] = {}
    for s in scenarios:
        by_family.setdefault(s.family, []).append(s)
    print(f"{len(scenarios)} scenarios generated in {dt:.2f} s ({len(scenarios) / dt:.0f}/s), seed {args.seed}")
    print(f"{'family':<14}{'count':>6}{'agents':>8}{'controllable':>14}{'roads':>7}{'ego goal m':>12}")
    for fam, group in sorted(by_family.items()):
        sums = [s.summary() for s in group]
        mean = lambda k: sum(x[k] for x in sums) / len(sums)  # noqa: E731
        print(f"{fam:<14}{len(group):>6}{mean('agents'):>8.1f}{mean('controllable'):>14.1f}"
              f"{mean('roads'):>7.0f}{mean('ego_goal_distance_m'):>12.1f}")
    return 0


# ----------------------------------------------------------------------------- anchor
def cmd_train_anchor(args: argparse.Namespace) -> int:
    _set_threads(args.threads)
    from sb3_contrib import RecurrentPPO

    from cpalgo.checkpoint import AtomicCheckpointCallback, save_model_atomic

    recipe = load_recipe(args.config)
    env = _make_env(recipe, args.seed)
    steps = args.timesteps or recipe.n_timesteps
    model = RecurrentPPO(recipe.policy, env, seed=args.seed, verbose=args.verbose,
                         tensorboard_log=args.tensorboard, **recipe.algo_kwargs)
    if args.init:  # continue from an earlier anchor (same recipe network)
        if not Path(args.init).is_file():
            raise SystemExit(f"--init: no such checkpoint {args.init!r}")
        model.set_parameters(args.init, exact_match=True)
    imitation = []
    t0 = time.perf_counter()
    if args.imitate:  # DAgger warm start from the tracking expert before PPO
        from cpalgo.pretrain import ImitationConfig, imitate_expert

        imitation = imitate_expert(model, config=ImitationConfig(iterations=args.imitate,
                                                                 num_worlds=args.imitate_worlds,
                                                                 epochs=args.imitate_epochs,
                                                                 beta=args.imitate_beta),
                                   seed=args.seed)
        if args.imitate_only:
            steps = 0
    out = Path(args.out)
    ckpt = AtomicCheckpointCallback(save_freq=max(1, 10 * recipe.algo_kwargs.get("n_steps", 64)), path=out)
    if steps:
        model.learn(steps, progress_bar=args.progress, callback=ckpt)
    wall = time.perf_counter() - t0
    if args.drop_optimizer_state:  # Adam's moments double the file; a later run restarts them
        policy = model.policy
        policy.optimizer = policy.optimizer_class(policy.parameters(), lr=model.lr_schedule(1.0),
                                                  **policy.optimizer_kwargs)
    save_model_atomic(model, out)
    rates = _outcomes(model, args.eval_tasks, recipe.env_kwargs.get("max_agents", 8))
    report = {"command": " ".join(sys.argv), "timesteps": int(model.num_timesteps), "wall_s": round(wall, 1),
              "normal_condition_outcomes": rates.as_dict()}
    if imitation:
        report["imitation_rounds"] = imitation
    from cpsim.atomic import atomic_path

    with atomic_path(str(out.with_suffix("")) + ".json") as tmp:
        Path(tmp).write_text(json.dumps(report, indent=2))
    print(f"anchor saved to {out} after {model.num_timesteps} steps in {wall:.0f} s")
    print(f"held-out outcomes under the normal condition: {rates}")
    return 0


# ----------------------------------------------------------------------------- post-train
def post_train(anchor: str | os.PathLike, config: str | os.PathLike, out_dir: str | os.PathLike,
               timesteps: int | None = None, seed: int = 0, eval_tasks: int = 256,
               progress: bool = True, verbose: int = 0, tensorboard: str | None = None,
               overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Post-train ``anchor`` with CounterPlay per the ``config`` recipe; returns the summary.

    Writes ``out_dir/counterplay.zip`` (atomically, also every few generations while
    training) and ``out_dir/summary.json`` / ``summary.md``.
    """
    from sb3_contrib import RecurrentPPO

    from cpalgo import CounterPlay
    from cpalgo.checkpoint import AtomicCheckpointCallback, save_model_atomic

    anchor = Path(anchor)
    if not anchor.is_file():
        raise SystemExit(f"--anchor: no such checkpoint {str(anchor)!r} (train one with `counterplay train-anchor`)")
    recipe = load_recipe(config)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    max_agents = int(recipe.env_kwargs.get("max_agents", 8))
    algo_kwargs = dict(recipe.algo_kwargs)
    algo_kwargs.update(overrides or {})

    env = _make_env(recipe, seed)
    model = CounterPlay(recipe.policy, env, seed=seed, verbose=verbose, tensorboard_log=tensorboard, **algo_kwargs)
    try:
        model.set_parameters(str(anchor), exact_match=True)
    except Exception as exc:
        raise SystemExit(f"--anchor: {anchor} does not match the recipe's policy ({exc})") from None
    before_model = RecurrentPPO.load(str(anchor), device="cpu")
    print(f"evaluating the anchor on {eval_tasks} held-out procedural tasks (normal condition) ...")
    before = _outcomes(before_model, eval_tasks, max_agents)
    print(f"  before: {before}")

    steps = timesteps or recipe.n_timesteps
    ckpt_path = out / "counterplay.zip"
    n_steps = int(algo_kwargs.get("n_steps", 128))
    ckpt = AtomicCheckpointCallback(save_freq=n_steps * 5, path=ckpt_path)
    t0 = time.perf_counter()
    model.learn(steps, progress_bar=progress, callback=ckpt)
    wall = time.perf_counter() - t0
    save_model_atomic(model, ckpt_path)
    after = _outcomes(model, eval_tasks, max_agents)
    print(f"  after:  {after}")

    budget = model.budget
    summary = {
        "anchor": str(anchor),
        "config": str(config),
        "checkpoint": str(ckpt_path),
        "timesteps": int(model.num_timesteps),
        "wall_s": round(wall, 1),
        "budget": budget.as_dict() if hasattr(budget, "as_dict") else dict(vars(budget)),
        "search": _search_summary(getattr(model, "search_totals", {}), model.panel),
        "held_out_tasks": eval_tasks,
        "outcomes_before": before.as_dict(),
        "outcomes_after": after.as_dict(),
    }
    _write_summary(out, summary)
    return summary


def _search_summary(totals: dict[str, float], panel: Sequence[str]) -> dict[str, Any]:
    """The search counters a reader wants, from CounterPlay's running totals."""
    keys = ("failures", "failures_collision", "failures_offroad", "failures_timeout", "searches",
            "searches_skipped", "factual_completed", "admissible", "teachers_chosen", "verified",
            "verification_failed", "teachers")
    out: dict[str, Any] = {k: int(totals.get(k, 0)) for k in keys}
    searches = out["searches"]
    out["mean_root_depth"] = round(totals.get("root_depth_sum", 0) / searches, 2) if searches else None
    out["winning_profiles"] = {name: int(totals.get(f"profile_{name}", 0)) for name in panel}
    out["search_cpu_s"] = round(float(totals.get("search_cpu_s", 0.0)), 2)
    return out


def _write_summary(out: Path, summary: dict[str, Any]) -> None:
    from cpalgo.evaluate.tables import write_text_atomic

    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2, default=str))
    b, a = summary["outcomes_before"], summary["outcomes_after"]
    lines = [
        "# CounterPlay post-training summary", "",
        f"- anchor: `{summary['anchor']}`, recipe `{summary['config']}`",
        f"- checkpoint: `{summary['checkpoint']}` after {summary['timesteps']} main transitions, "
        f"{summary['wall_s']} s",
        f"- search: {json.dumps(summary['search'], default=str)}",
        f"- budget: {json.dumps(summary['budget'], default=str)}", "",
        f"Held-out procedural tasks ({summary['held_out_tasks']}), self-play, normal condition:", "",
        "| | goal | collision | off-road | timeout | agents |", "|---|---|---|---|---|---|",
        f"| anchor | {b['goal']:.1%} | {b['collision']:.1%} | {b['offroad']:.1%} | {b['timeout']:.1%} | {b['agents']} |",
        f"| CounterPlay | {a['goal']:.1%} | {a['collision']:.1%} | {a['offroad']:.1%} | {a['timeout']:.1%} | {a['agents']} |",
    ]
    write_text_atomic(out / "summary.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


def cmd_post_train(args: argparse.Namespace) -> int:
    _set_threads(args.threads)
    post_train(args.anchor, args.config, args.out, timesteps=args.timesteps, seed=args.seed,
               eval_tasks=args.eval_tasks, progress=args.progress, verbose=args.verbose,
               tensorboard=args.tensorboard)
    return 0


def cmd_outcomes(args: argparse.Namespace) -> int:
    from sb3_contrib import RecurrentPPO

    if args.model == "expert":  # the tracking expert, the imitation teacher
        from cpalgo.selfplay_eval import expert_outcomes

        print(expert_outcomes(_held_out(args.tasks), condition=args.condition, max_agents=args.max_agents,
                              config={"dynamics": args.dynamics}))
        return 0
    path = Path(args.model)
    if not path.is_file():
        raise SystemExit(f"--model: no such checkpoint {str(path)!r}")
    try:
        model = RecurrentPPO.load(str(path), device="cpu")
    except Exception as exc:
        raise SystemExit(f"--model: {path} does not load as a RecurrentPPO checkpoint ({exc})") from None
    print(_outcomes(model, args.tasks, args.max_agents, args.condition))
    return 0


# ----------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="counterplay", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
        p.add_argument("--verbose", type=int, default=0)
        p.add_argument("--tensorboard", default=None, help="tensorboard log folder")
        p.add_argument("--no-progress", dest="progress", action="store_false", help="hide the progress bar")

    run = sub.add_parser("run", help="post-train the shipped anchor on procedural scenarios (main job)")
    common(run)
    run.add_argument("--out", default="runs/counterplay")
    run.add_argument("--timesteps", type=_positive_int, default=None)
    run.add_argument("--eval-tasks", type=_positive_int, default=256)
    run.set_defaults(func=cmd_post_train, anchor=str(DEFAULT_ANCHOR), config=str(DEFAULT_POST_CONFIG))

    pt = sub.add_parser("post-train", help="CounterPlay post-training of an anchor checkpoint")
    common(pt)
    pt.add_argument("--anchor", default=str(DEFAULT_ANCHOR))
    pt.add_argument("--config", default=str(DEFAULT_POST_CONFIG), help="zoo YAML recipe")
    pt.add_argument("--out", default="runs/counterplay")
    pt.add_argument("--timesteps", type=_positive_int, default=None)
    pt.add_argument("--eval-tasks", type=_positive_int, default=256)
    pt.set_defaults(func=cmd_post_train)

    ta = sub.add_parser("train-anchor", help="train the reward-conditioned self-play anchor")
    common(ta)
    ta.add_argument("--config", default=str(DEFAULT_ANCHOR_CONFIG), help="zoo YAML recipe")
    ta.add_argument("--out", default="runs/anchor/anchor.zip")
    ta.add_argument("--timesteps", type=_positive_int, default=None)
    ta.add_argument("--init", default=None, help="start from this anchor checkpoint's weights")
    ta.add_argument("--imitate", type=_non_negative_int, default=0, metavar="ROUNDS",
                    help="DAgger rounds imitating cpsim.expert.TrackingExpert before PPO (default 0: none)")
    ta.add_argument("--imitate-worlds", type=_positive_int, default=128, help="worlds per DAgger round")
    ta.add_argument("--imitate-epochs", type=_positive_int, default=10,
                    help="passes over the kept DAgger data per round")
    ta.add_argument("--imitate-beta", type=_unit_float, default=1.0,
                    help="probability that the expert drives in the first DAgger round (lower it when "
                         "continuing an imitation run with --init)")
    ta.add_argument("--imitate-only", action="store_true", help="stop after the imitation rounds (no PPO)")
    ta.add_argument("--drop-optimizer-state", action="store_true",
                    help="save the final checkpoint with a fresh optimiser (weights only: about half the size)")
    ta.add_argument("--eval-tasks", type=_positive_int, default=256)
    ta.set_defaults(func=cmd_train_anchor)

    oc = sub.add_parser("outcomes", help="self-play outcome rates of a checkpoint on held-out tasks")
    oc.add_argument("--model", default=str(DEFAULT_ANCHOR),
                    help="checkpoint, or 'expert' for cpsim.expert.TrackingExpert")
    oc.add_argument("--dynamics", default="jerk", choices=["jerk", "classic"],
                    help="dynamics of the simulator for --model expert")
    oc.add_argument("--tasks", type=_positive_int, default=256)
    oc.add_argument("--max-agents", type=_positive_int, default=8)
    oc.add_argument("--condition", default="normal")
    oc.set_defaults(func=cmd_outcomes)

    po = sub.add_parser("pool", help="generate and summarise a procedural scenario pool")
    po.add_argument("--n", type=_positive_int, default=60)
    po.add_argument("--seed", type=int, default=0)
    po.add_argument("--families", nargs="*", default=None)
    po.set_defaults(func=cmd_pool)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
