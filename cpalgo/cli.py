"""The ``counterplay`` command.

Sub-commands (``counterplay SUB-COMMAND --help`` lists each one's options and defaults):

* ``run``: post-train the shipped anchor with PPO-Continue and with CounterPlay at the same
  budget and seed, evaluate the anchor and both on the same held-out tasks, write the
  checkpoints, tables and a summary (the README's main job; :mod:`cpalgo.experiments.mainjob`);
* ``post-train``: CounterPlay alone, with every option exposed;
* ``experiment``: a grid of methods x seeds on Ray or in-process, with the paper's tables;
* ``methods``: the registered post-training methods, one line each;
* ``train-anchor``: train the reward-conditioned self-play anchor (RecurrentPPO);
* ``outcomes``: self-play outcome rates of a checkpoint on held-out tasks;
* ``pool``: generate and summarise a procedural scenario pool;
* ``searches``: list the searches a CounterPlay run kept; draw one (PNG / GIF).

Paths spelled ``zoo/NAME`` (the README's) name the files shipped inside the package when
no such file exists (:func:`cpalgo.recipes.resolve_path`). A wrong argument or a file that
is missing or does not fit ends the command with one ``error:`` line and exit status 2,
as argparse does for its own errors.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

from cpalgo.common.checks import UsageError, check_out_path, load_womd_option
from cpalgo.common.checks import non_negative_int as _non_negative_int
from cpalgo.common.checks import positive_int as _positive_int
from cpalgo.common.checks import set_threads as _set_threads
from cpalgo.recipes import Recipe, import_string, load_recipe, resolve_path

#: Teacher names of ``--teacher`` (cpsim.expert.EXPERTS; kept here so the parser imports no Warp).
TEACHERS: tuple[str, ...] = ("tracking", "reactive", "reactive-v2", "reactive-v1", "reactive-v4", "reactive-v5",
                             "reactive-v6", "reactive-v7")

#: Defaults, spelled as the README spells them (they resolve to the shipped files).
DEFAULT_ANCHOR = "zoo/anchor.zip"
DEFAULT_ANCHOR_CONFIG = "zoo/anchor.yml"
DEFAULT_POST_CONFIG = "zoo/counterplay.yml"
#: Held-out tasks come from the evaluation seed range (disjoint from training by seed).
HELD_OUT_SEED = 0


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("counterplay")
    except PackageNotFoundError:  # running from a source tree that is not installed
        import cpsim

        return cpsim.__version__


# ----------------------------------------------------------------------------- argument types
def _unit_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text}")
    return value


def _non_negative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or value < 0.0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def _condition(text: str) -> str | list[float]:
    """A profile name or 10 comma-separated raw values, validated."""
    from cpsim.conditions import resolve_condition

    spec: str | list[float] = text
    if "," in text:
        try:
            spec = [float(v) for v in text.split(",")]
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a profile name or 10 numbers, got {text!r}") from None
    try:
        resolve_condition(spec, "condition")
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("condition: ")) from None
    return spec


def _existing_file(text: str) -> str:
    path = resolve_path(text)
    if not os.path.isfile(path):
        raise argparse.ArgumentTypeError(f"no such file {text!r}")
    return path


def _existing_dir(text: str) -> str:
    if not os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"no such folder {text!r}")
    return text


def _recipe_file(text: str) -> str:
    """A zoo YAML recipe that parses (the path, resolved)."""
    try:
        return load_recipe(text).path
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("config: ")) from None


# ----------------------------------------------------------------------------- helpers
def check_algorithm_arguments(cls: type, recipe: Recipe, argument: str = "--config", **extra: Any) -> None:
    """``UsageError`` naming the recipe file and the setting when ``cls`` (an SB3 algorithm)
    rejects one of the recipe's algorithm arguments (plus ``extra``), or the recipe's
    env_kwargs are not valid :class:`cpsim.SelfPlayVecEnv` arguments. Nothing is built: the
    algorithm is constructed without env and network, which runs its argument checks only."""
    from cpalgo.methods import algorithm_parameters, check_algorithm_values
    from cpsim.envs.selfplay import check_selfplay_arguments

    kwargs = {**recipe.algo_kwargs, **extra}
    unknown = sorted(set(kwargs) - algorithm_parameters(cls))
    if unknown:
        raise UsageError(f"{argument}: {recipe.path}: {unknown[0]!r} is not an argument of {cls.__name__}")
    try:
        check_algorithm_values(cls, kwargs, recipe.policy)
    except (TypeError, ValueError) as exc:
        raise UsageError(f"{argument}: {recipe.path}: {exc}") from None
    try:
        check_selfplay_arguments(**recipe.env_kwargs)
    except (TypeError, ValueError) as exc:
        raise UsageError(f"{argument}: {recipe.path}: env_kwargs: {exc}") from None


def _brief(exc: BaseException, lines: int = 2) -> str:
    """The first non-empty lines of an exception's message (torch's state-dict mismatch
    lists every tensor)."""
    return " ".join([line.strip() for line in str(exc).splitlines() if line.strip()][:lines])


def _make_env(recipe: Recipe, seed: int, num_worlds: int | None = None, **overrides: Any) -> Any:
    """The recipe's self-play env with its ``vec_env_wrapper`` list (a ``VecMonitor`` first
    when the list has none: it gives SB3 its episode statistics)."""
    from stable_baselines3.common.vec_env import VecMonitor

    import cpsim

    if recipe.zoo_only:
        raise UsageError(f"--config: {sorted(recipe.zoo_only)} in {recipe.path} are applied by rl-zoo3 only "
                         "(python -m cpalgo.zoo train); remove them for the counterplay command")
    if recipe.normalize is not None:
        raise UsageError(f"--config: normalize in {recipe.path}: the counterplay command evaluates and "
                         "post-trains on raw observations (as the shipped anchor was trained); train with "
                         "normalisation through python -m cpalgo.zoo train")
    try:
        wrappers = [(import_string(name), kwargs) for name, kwargs in recipe.vec_env_wrappers]
    except ValueError as exc:
        raise UsageError(f"--config: vec_env_wrapper in {recipe.path}: {exc}") from None
    kwargs = dict(recipe.env_kwargs)
    kwargs.update(overrides)
    kwargs.setdefault("seed", seed)
    env = cpsim.SelfPlayVecEnv(num_worlds=num_worlds or recipe.num_worlds, **kwargs)
    # attribute access (env.sim, env.obs_layout) passes through the wrappers
    if not any(isinstance(cls, type) and issubclass(cls, VecMonitor) for cls, _ in wrappers):
        env = VecMonitor(env)
    for cls, kw in wrappers:
        env = cls(env, **kw)
    return env


@functools.lru_cache(maxsize=4)
def _held_out(n: int) -> tuple:
    """The first ``n`` held-out tasks (generated once per process: before and after share them)."""
    from cpsim.scenario import eval_pool

    return tuple(eval_pool(n, seed=HELD_OUT_SEED))


def _outcomes(model: Any, n_tasks: int, max_agents: int, condition: Any = "normal") -> Any:
    from cpalgo.anchor.outcomes import selfplay_outcomes

    return selfplay_outcomes(model, _held_out(n_tasks), condition=condition, max_agents=max_agents)


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    from cpalgo.evaluate.tables import write_text_atomic

    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(doc, indent=2, default=str) + "\n")


# ----------------------------------------------------------------------------- pool
def cmd_pool(args: argparse.Namespace) -> int:
    from cpsim.scenario import FAMILIES, pool

    families = args.families or None
    if families:
        unknown = sorted(set(families) - set(FAMILIES))
        if unknown:
            raise UsageError(f"--families: unknown {unknown}; accepted: {list(FAMILIES)}")
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

        def mean(key: str, sums: list = sums) -> float:
            return sum(x[key] for x in sums) / len(sums)

        print(f"{fam:<14}{len(group):>6}{mean('agents'):>8.1f}{mean('controllable'):>14.1f}"
              f"{mean('roads'):>7.0f}{mean('ego_goal_distance_m'):>12.1f}")
    return 0


# ----------------------------------------------------------------------------- anchor
_RUN_CONFLICTS = ("out", "init", "imitate", "imitate_only", "teacher_coef", "teacher_style_pairs", "drop_optimizer_state")


def _train_anchor_run(args: argparse.Namespace) -> int:
    """``--run-dir`` / ``--resume``: self-play PPO from scratch in resumable segments."""
    from cpalgo.anchor.selfplay import AnchorRunSettings, train_anchor_run

    defaults = {"out": "runs/anchor/anchor.zip", "init": None, "imitate": 0, "imitate_only": False,
                "teacher_coef": 0.0, "teacher_style_pairs": 0, "drop_optimizer_state": False}
    used = [f"--{k.replace('_', '-')}" for k in _RUN_CONFLICTS if getattr(args, k) != defaults[k]]
    if used:
        raise UsageError(f"{', '.join(used)}: not used by a --run-dir / --resume run (self-play PPO from scratch)")
    stop = None if args.stop_after is None else 60.0 * args.stop_after
    command = "counterplay " + " ".join(sys.argv[1:]) if sys.argv and sys.argv[0] else None
    try:
        if args.resume:
            if args.run_dir:
                raise UsageError("--run-dir / --resume: give one (--resume RUN_DIR continues that run)")
            if not os.path.isdir(args.resume):
                raise UsageError(f"--resume: no such folder {args.resume!r}")
            train_anchor_run(args.resume, resume=True, stop_after_s=stop, command=command)
            return 0
        settings = AnchorRunSettings(
            recipe=args.config, seed=args.seed, timesteps=args.timesteps or load_recipe(args.config).n_timesteps,
            segment_timesteps=args.segment, pool_size=args.pool_size, womd_dir=args.add_womd,
            eval_tasks=args.eval_tasks, threads=args.threads)
        train_anchor_run(args.run_dir, settings, stop_after_s=stop, command=command)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return 0


def cmd_curve(args: argparse.Namespace) -> int:
    from cpalgo.anchor.selfplay import plot_curve, read_curve

    try:
        path = plot_curve(args.run_dir, args.out)
        rows = read_curve(args.run_dir)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    last = rows[-1]
    print(f"{path}: {len(rows)} points, last at {last['timesteps'] / 1e6:.1f}M transitions "
          f"({last['wall_s'] / 3600:.2f} h): held-out goal aggressive / normal / cautious "
          f"{last['aggressive_goal']:.1%} / {last['normal_goal']:.1%} / {last['cautious_goal']:.1%}")
    return 0


def cmd_train_anchor(args: argparse.Namespace) -> int:
    if args.run_dir or args.resume:
        return _train_anchor_run(args)
    _set_threads(args.threads)

    from cpalgo.checkpoint import AtomicCheckpointCallback, save_model_atomic

    if (args.teacher_style_pairs or args.style_pair_coef is not None or args.style_pair_focus) \
            and not args.teacher_coef > 0:
        raise UsageError("--teacher-style-pairs / --style-pair-coef / --style-pair-focus: need --teacher-coef > 0 "
                         "(TeacherPPO)")
    if args.style_pair_focus and not args.teacher_style_pairs:
        raise UsageError("--style-pair-focus: needs --teacher-style-pairs K > 0")
    recipe = load_recipe(args.config)
    out = check_out_path(args.out, "--out", folder=False)
    if args.teacher_coef > 0:
        from cpalgo.anchor.teacher_ppo import TeacherPPO as algorithm_class
    else:
        from cpalgo.counterplay.algorithm import CounterPlay as algorithm_class
    check_algorithm_arguments(algorithm_class, recipe)
    overrides = {}
    if args.add_womd:  # the recipe's procedural pool plus real scenes
        from cpsim.envs.selfplay import resolve_scenarios

        kw = recipe.env_kwargs
        pool = resolve_scenarios(family=kw.get("family"), num_scenarios=kw.get("num_scenarios"), seed=args.seed)
        overrides = {"scenarios": pool + load_womd_option(args.add_womd), "family": None, "num_scenarios": None}
    env = _make_env(recipe, args.seed, **overrides)
    steps = args.timesteps or recipe.n_timesteps
    if args.teacher_coef > 0:  # PPO with the teacher's actions as an auxiliary imitation term
        from cpalgo.anchor.teacher_ppo import TeacherPPO

        model = TeacherPPO(recipe.policy, env, teacher=args.teacher, teacher_coef=args.teacher_coef,
                           teacher_coef_final=args.teacher_coef_final, style_pairs=args.teacher_style_pairs,
                           style_pair_coef=args.style_pair_coef,
                           style_pair_focus=args.style_pair_focus, seed=args.seed, verbose=args.verbose,
                           tensorboard_log=args.tensorboard, **recipe.algo_kwargs)
    else:  # plain PPO on the fast learner (fused LSTM, live slots only); shipped as RecurrentPPO below
        from cpalgo.counterplay.algorithm import CounterPlay

        model = CounterPlay(recipe.policy, env, counterfactual=False, seed=args.seed, verbose=args.verbose,
                            tensorboard_log=args.tensorboard, **recipe.algo_kwargs)
    if args.init:  # continue from an earlier anchor (same recipe network)
        try:
            model.set_parameters(args.init, exact_match=True)
        except Exception as exc:  # noqa: BLE001 - reported with the file name
            raise UsageError(f"--init: {args.init} does not match the recipe's policy ({_brief(exc)})") from None
    imitation = []
    t0 = time.perf_counter()
    if args.imitate:  # DAgger warm start from an expert teacher before PPO
        from cpalgo.anchor.imitation import ImitationConfig, imitate_expert

        imitation = imitate_expert(model, config=ImitationConfig(iterations=args.imitate,
                                                                 num_worlds=args.imitate_worlds,
                                                                 epochs=args.imitate_epochs,
                                                                 beta=args.imitate_beta,
                                                                 teacher=args.teacher,
                                                                 style_pairs=args.imitate_style_pairs),
                                   seed=args.seed)
        if args.imitate_only:
            steps = 0
    ckpt = AtomicCheckpointCallback(save_freq=max(1, 10 * recipe.algo_kwargs.get("n_steps", 64)), path=out)
    if steps:
        model.learn(steps, progress_bar=args.progress, callback=ckpt)
    wall = time.perf_counter() - t0
    from cpalgo.anchor.teacher_ppo import export_recurrent_ppo

    # ship a plain sb3-contrib RecurrentPPO with the same weights and Adam state
    model = export_recurrent_ppo(model, recipe.policy, env, seed=args.seed, **recipe.algo_kwargs)
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
    _write_json(Path(str(out.with_suffix("")) + ".json"), report)
    print(f"anchor saved to {out} after {model.num_timesteps} steps in {wall:.0f} s")
    print(f"held-out outcomes under the normal condition: {rates}")
    return 0


# ----------------------------------------------------------------------------- post-train
def post_train(anchor: str | os.PathLike = DEFAULT_ANCHOR, config: str | os.PathLike = DEFAULT_POST_CONFIG,
               out_dir: str | os.PathLike = "runs/counterplay", timesteps: int | None = None, seed: int = 0,
               eval_tasks: int = 256, progress: bool = True, verbose: int = 0, tensorboard: str | None = None,
               overrides: dict[str, Any] | None = None, worlds: int | None = None,
               scenarios: int | None = None) -> dict[str, Any]:
    """Post-train ``anchor`` with CounterPlay per the ``config`` recipe; returns the summary.

    ``anchor`` and ``config`` go through :func:`cpalgo.recipes.resolve_path` (``zoo/...``
    names the shipped files). ``worlds`` overrides the recipe's number of training worlds
    (``n_envs / max_agents``), ``scenarios`` its ``num_scenarios``. Writes ``out_dir/counterplay.zip`` (atomically, also every
    few generations while training) and ``out_dir/summary.json`` / ``summary.md``.
    Raises :class:`UsageError` when a file is missing or the anchor does not fit the recipe.
    """
    from sb3_contrib import RecurrentPPO

    from cpalgo import CounterPlay
    from cpalgo.checkpoint import AtomicCheckpointCallback, save_model_atomic

    anchor = Path(resolve_path(anchor))
    if not anchor.is_file():
        raise UsageError(f"--anchor: no such checkpoint {str(anchor)!r} (train one with `counterplay train-anchor`)")
    try:
        recipe = load_recipe(config)
    except ValueError as exc:
        raise UsageError(f"--config: {exc}") from None
    check_algorithm_arguments(CounterPlay, recipe, **(overrides or {}))
    out = check_out_path(out_dir, "--out", folder=True)
    out.mkdir(parents=True, exist_ok=True)
    max_agents = int(recipe.env_kwargs.get("max_agents", 8))
    algo_kwargs = dict(recipe.algo_kwargs)
    algo_kwargs.update(overrides or {})

    env = _make_env(recipe, seed, num_worlds=worlds, **({} if scenarios is None else {"num_scenarios": scenarios}))
    model = CounterPlay(recipe.policy, env, seed=seed, verbose=verbose, tensorboard_log=tensorboard, **algo_kwargs)
    try:
        model.set_parameters(str(anchor), exact_match=True)
    except Exception as exc:  # noqa: BLE001 - reported with the file name
        raise UsageError(f"--anchor: {anchor} does not match the recipe's policy ({_brief(exc)})") from None
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
    search_files = _write_searches(model, ckpt_path)
    after = _outcomes(model, eval_tasks, max_agents)
    print(f"  after:  {after}")

    summary = {
        "anchor": str(anchor),
        "config": recipe.path,
        "checkpoint": str(ckpt_path),
        "timesteps": int(model.num_timesteps),
        "wall_s": round(wall, 1),
        "budget": model.budget.as_dict(),
        "search": _search_summary(getattr(model, "search_totals", {}), model.panel),
        "held_out_tasks": eval_tasks,
        "outcomes_before": before.as_dict(),
        "outcomes_after": after.as_dict(),
    }
    summary["search_files"] = search_files
    _write_summary(out, summary)
    return summary


def _search_summary(totals: dict[str, float], panel: Sequence[str]) -> dict[str, Any]:
    """The search counters a reader wants, from CounterPlay's running totals."""
    from cpalgo.counterplay.search import ADMISSION_VERDICTS

    keys = ("failures", "failures_collision", "failures_offroad", "failures_timeout", "searches",
            "searches_skipped", "factual_completed", "admissible", "teachers_chosen", "verified",
            "verification_failed", "teachers")
    out: dict[str, Any] = {k: int(totals.get(k, 0)) for k in keys}
    searches = out["searches"]
    out["mean_root_depth"] = round(totals.get("root_depth_sum", 0) / searches, 2) if searches else None
    out["winning_profiles"] = {name: int(totals.get(f"profile_{name}", 0)) for name in panel}
    out["retry_verdicts"] = {name: int(totals.get(f"retries_{name}", 0)) for name in ADMISSION_VERDICTS}
    out["search_cpu_s"] = round(float(totals.get("search_cpu_s", 0.0)), 2)
    return out


def _md_value(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict):
        return ", ".join(f"{k} {_md_value(v)}" for k, v in value.items()) or "none"
    return "n/a" if value is None else str(value)


def _md_table(title: str, values: dict[str, Any]) -> list[str]:
    """A two-column Markdown table (one row per key) under a heading."""
    rows = [f"| {key.replace('_', ' ')} | {_md_value(value)} |" for key, value in values.items()]
    return [f"## {title}", "", "| | |", "|---|---|", *rows, ""]


def _write_summary(out: Path, summary: dict[str, Any]) -> None:
    from cpalgo.evaluate.tables import write_text_atomic

    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2, default=str))
    b, a = summary["outcomes_before"], summary["outcomes_after"]
    lines = [
        "# CounterPlay post-training summary", "",
        f"- anchor: `{summary['anchor']}`, recipe `{summary['config']}`",
        f"- checkpoint: `{summary['checkpoint']}` after {summary['timesteps']} main transitions, "
        f"{summary['wall_s']} s", "",
        f"Held-out procedural tasks ({summary['held_out_tasks']}), self-play, normal condition:", "",
        "| | goal | collision | off-road | timeout | agents |", "|---|---|---|---|---|---|",
        f"| anchor | {b['goal']:.1%} | {b['collision']:.1%} | {b['offroad']:.1%} | {b['timeout']:.1%} | {b['agents']} |",
        f"| CounterPlay | {a['goal']:.1%} | {a['collision']:.1%} | {a['offroad']:.1%} | {a['timeout']:.1%} | {a['agents']} |",
        "",
        *_md_table("Search", summary["search"]),
        *_md_table("Budget (transitions)", summary["budget"]),
    ]
    write_text_atomic(out / "summary.md", "\n".join(lines))
    print("\n".join(lines))


def cmd_post_train(args: argparse.Namespace) -> int:
    _set_threads(args.threads)
    post_train(args.anchor, args.config, args.out, timesteps=args.timesteps, seed=args.seed,
               eval_tasks=args.eval_tasks, progress=args.progress, verbose=args.verbose,
               tensorboard=args.tensorboard, worlds=args.worlds, scenarios=args.scenarios)
    return 0


def _write_searches(model: Any, ckpt_path: Path) -> dict[str, str]:
    """The kept searches beside the checkpoint, and the figure of the latest verified one
    (``search.png`` in the same folder) when there is one."""
    from cpalgo.viz import write_search_files

    files = write_search_files(model, ckpt_path)
    if files:
        print(f"kept searches: {files}")
    return files


def cmd_searches(args: argparse.Namespace) -> int:
    from cpalgo.counterplay.records import failure_anatomy, format_anatomy, format_table, load_records, searches_path

    path = searches_path(args.model)
    if not path.is_file():
        raise UsageError(f"--model: no search file {str(path)!r} (counterfactual CounterPlay runs write it beside "
                         "their checkpoint; PPO baselines, distillation controls and runs with keep_searches=0 "
                         "keep none)")
    try:
        records = load_records(path)
    except ValueError as exc:
        raise UsageError(f"--model: {exc}") from None
    if args.show is None:
        print(f"{len(records)} searches kept in {path}")
        if records:
            print(format_table(records))
            print(format_anatomy(failure_anatomy(records)))
        return 0
    if not 0 <= args.show < len(records):
        raise UsageError(f"--show: index {args.show} outside 0..{len(records) - 1} ({len(records)} searches kept)")
    from cpalgo.viz import render_search

    out = str(check_out_path(args.out or f"search_{args.show}.png", "--out", folder=False))
    try:
        written = render_search(records[args.show], out)
    except ValueError as exc:
        raise UsageError(f"--out: {exc}") from None
    print(records[args.show].summary())
    print(f"written to {written}")
    return 0


# ----------------------------------------------------------------------------- outcomes
def cmd_outcomes(args: argparse.Namespace) -> int:
    _set_threads(args.threads)
    check_out_path(args.out, "--out", folder=False)
    if args.model == "expert":  # an imitation teacher
        from cpalgo.anchor.outcomes import expert_outcomes

        rates = expert_outcomes(_held_out(args.tasks), condition=args.condition, max_agents=args.max_agents,
                                config={"dynamics": args.dynamics}, teacher=args.teacher)
    else:
        from cpalgo.evaluate.runner import load_model

        path = resolve_path(args.model)
        try:
            model = load_model(path, "--model")
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        rates = _outcomes(model, args.tasks, args.max_agents, args.condition)
    print(rates)
    out = Path(args.out)
    extra = {"teacher": args.teacher} if args.model == "expert" else {}
    _write_json(out, {"model": args.model if args.model == "expert" else path, **extra, "condition": args.condition,
                      "tasks": args.tasks, "max_agents": args.max_agents, "outcomes": rates.as_dict()})
    print(f"written to {out}")
    return 0


# ----------------------------------------------------------------------------- parser
class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows ``(default: ...)`` where a default says something (not None, not a flag)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if action.default is None or isinstance(action.default, bool) or action.default is argparse.SUPPRESS:
            return action.help or ""
        return super()._get_help_string(action) or ""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="counterplay",
        description="Counterfactual post-training (CounterPlay) of self-play driving policies on the "
                    "cpsim batched simulator.",
        epilog="Paths spelled zoo/NAME name the recipes and checkpoints shipped with the package. "
               "Run `counterplay SUB-COMMAND --help` for the options of each sub-command.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="SUB-COMMAND")

    def add(name: str, help: str, description: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help, description=description, formatter_class=_HelpFormatter)
        p.set_defaults(parser=p)
        return p

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("--seed", type=_non_negative_int, default=0,
                       help="seed of the env, the algorithm and the scenario draws")
        p.add_argument("--threads", type=_positive_int, default=None, help="torch threads (default: torch's)")
        p.add_argument("--verbose", type=int, default=0, choices=[0, 1, 2], help="SB3 verbosity")
        p.add_argument("--tensorboard", default=None, metavar="DIR", help="write tensorboard logs to DIR")
        p.add_argument("--no-progress", dest="progress", action="store_false", help="hide the progress bar")

    def post_options(p: argparse.ArgumentParser, out_help: str, timesteps_help: str) -> None:
        p.add_argument("--out", default="runs/counterplay", metavar="DIR", help=out_help)
        p.add_argument("--timesteps", type=_positive_int, default=None, metavar="N", help=timesteps_help)
        p.add_argument("--worlds", type=_positive_int, default=None, metavar="W",
                       help="training worlds; a rollout is W x max_agents x n_steps transitions "
                            "(default: the recipe's n_envs / max_agents)")
        p.add_argument("--scenarios", type=_positive_int, default=None, metavar="N",
                       help="procedural training scenarios to generate (default: the recipe's "
                            "env_kwargs.num_scenarios)")
        p.add_argument("--eval-tasks", type=_positive_int, default=256, metavar="N",
                       help="held-out procedural tasks evaluated before and after")

    run = add("run", "post-train the shipped anchor with PPO-Continue and CounterPlay (the main job)",
              f"Post-train the shipped self-play anchor ({DEFAULT_ANCHOR}) with PPO-Continue and with "
              f"CounterPlay at the same budget and seed on the procedural training pool "
              f"({DEFAULT_POST_CONFIG}), evaluate the anchor and both on the same held-out tasks "
              "(both splits, all traffic regimes: score, completion, at-fault collisions, timeouts, "
              "failure repair), and write the checkpoints, tables and a summary. --eval-tasks counts "
              "tasks per split.")
    common(run)
    post_options(run, "folder for the grid: runs/<method>/seed0/model.zip, results.csv, tables.md, "
                      "summary.md, summary.json and plots (a rerun resumes what is there)",
                 "B_post of each method: every agent transition, main or branch, counts, and both methods "
                 "stop at N (default: the recipe's n_timesteps)")
    from cpalgo.anchor.compress import add_command as add_compress_command
    from cpalgo.experiments.command import add_commands, main_job_defaults

    run.set_defaults(anchor=DEFAULT_ANCHOR, config=DEFAULT_POST_CONFIG, **main_job_defaults())

    pt = add("post-train", "CounterPlay post-training of an anchor checkpoint",
             "CounterPlay post-training of an anchor checkpoint with a zoo YAML recipe.")
    common(pt)
    pt.add_argument("--anchor", type=_existing_file, default=DEFAULT_ANCHOR, metavar="ZIP",
                    help="anchor checkpoint (RecurrentPPO with the recipe's network)")
    pt.add_argument("--config", type=_recipe_file, default=DEFAULT_POST_CONFIG, metavar="YAML",
                    help="zoo YAML recipe")
    post_options(pt, "folder for counterplay.zip (and its .searches.npz), summary.json and summary.md",
                 "main transitions to train (default: the recipe's n_timesteps); training stops after the "
                 "rollout that reaches N")
    pt.set_defaults(func=cmd_post_train)

    ta = add("train-anchor", "train the reward-conditioned self-play anchor",
             "Train the reward-conditioned self-play anchor (RecurrentPPO), optionally after a DAgger "
             "warm start that imitates an expert teacher (cpsim.expert).")
    common(ta)
    ta.add_argument("--config", type=_recipe_file, default=DEFAULT_ANCHOR_CONFIG, metavar="YAML",
                    help="zoo YAML recipe")
    ta.add_argument("--out", default="runs/anchor/anchor.zip", metavar="ZIP",
                    help="checkpoint to write (its report goes next to it as .json)")
    ta.add_argument("--timesteps", type=_positive_int, default=None, metavar="N",
                    help="PPO transitions (default: the recipe's n_timesteps)")
    ta.add_argument("--init", type=_existing_file, default=None, metavar="ZIP",
                    help="start from this anchor checkpoint's weights")
    ta.add_argument("--imitate", type=_non_negative_int, default=0, metavar="ROUNDS",
                    help="DAgger rounds imitating the --teacher before PPO (0: none)")
    ta.add_argument("--teacher", default="tracking", choices=TEACHERS,
                    help="imitation teacher: tracking (cpsim.expert.TrackingExpert, follows its log), "
                         "reactive (cpsim.expert.ReactiveExpert, keeps gaps, yields, slows for curves and for its goal "
                         "speed, speed by condition), or one of its versioned styles (cpsim.expert.REACTIVE_STYLE_V*): "
                         "reactive-v1 (first), reactive-v2 (no goal speed limit), reactive-v4 (v3 with one curve "
                         "speed), reactive-v5 (bolder aggressive end), reactive-v6 (v5 with one curve speed), "
                         "reactive-v7 (v6 with the goal brake)")
    ta.add_argument("--add-womd", type=_existing_dir, default=None, metavar="DIR",
                    help="add the WOMD scenes of this folder to the recipe's procedural training pool")
    ta.add_argument("--imitate-worlds", type=_positive_int, default=128, metavar="W", help="worlds per DAgger round")
    ta.add_argument("--imitate-epochs", type=_positive_int, default=10, metavar="N",
                    help="passes over the kept DAgger data per round")
    ta.add_argument("--imitate-beta", type=_unit_float, default=1.0, metavar="P",
                    help="probability that the expert drives in the first DAgger round (lower it when "
                         "continuing an imitation run with --init)")
    ta.add_argument("--imitate-style-pairs", type=_non_negative_int, default=0, metavar="K",
                    help="label every DAgger episode K more times with every agent's style swapped for a random "
                         "panel profile's (the teacher's actions under it at the same states), so the student "
                         "learns how the style changes the action (cpalgo.anchor.imitation.ImitationConfig.style_pairs)")
    ta.add_argument("--imitate-only", action="store_true", help="stop after the imitation rounds (no PPO)")
    ta.add_argument("--teacher-coef", type=_non_negative_float, default=0.0, metavar="C",
                    help="PPO with the --teacher's actions as an auxiliary imitation term of weight C "
                         "(cpalgo.anchor.teacher_ppo.TeacherPPO; 0: plain PPO)")
    ta.add_argument("--teacher-coef-final", type=_non_negative_float, default=None, metavar="C",
                    help="the imitation weight at the end of PPO (linear from --teacher-coef; default: constant)")
    ta.add_argument("--teacher-style-pairs", type=_non_negative_int, default=0, metavar="K",
                    help="with --teacher-coef: label every live decision K more times under a swapped panel style "
                         "and imitate those labels too (cpalgo.anchor.teacher_ppo.TeacherPPO.style_pairs)")
    ta.add_argument("--style-pair-coef", type=_non_negative_float, default=None, metavar="C",
                    help="weight of the swapped-style imitation term (default: the current --teacher-coef)")
    ta.add_argument("--style-pair-focus", action="store_true",
                    help="average the swapped-style term only over decisions whose swapped label differs from the "
                         "agent's own (cpalgo.anchor.teacher_ppo.TeacherPPO.style_pair_focus)")
    ta.add_argument("--drop-optimizer-state", action="store_true",
                    help="save the final checkpoint with a fresh optimiser (weights only: about half the size)")
    ta.add_argument("--eval-tasks", type=_positive_int, default=256, metavar="N",
                    help="held-out procedural tasks evaluated at the end")
    ta.add_argument("--run-dir", default=None, metavar="DIR",
                    help="self-play PPO from scratch in resumable segments, in this new run folder (checkpoint.zip, "
                         "curve.csv, run.json; cpalgo.anchor.selfplay); --timesteps is the run's whole budget")
    ta.add_argument("--resume", default=None, metavar="RUN_DIR",
                    help="continue the run in RUN_DIR from its last checkpoint (settings from its run.json)")
    ta.add_argument("--segment", type=_positive_int, default=10_000_000, metavar="N",
                    help="with --run-dir: transitions between checkpoints, curve points and pool draws")
    ta.add_argument("--pool-size", type=_positive_int, default=512, metavar="N",
                    help="with --run-dir: procedural training scenes drawn for every segment")
    ta.add_argument("--stop-after", type=float, default=None, metavar="MINUTES",
                    help="with --run-dir / --resume: stop cleanly after the segment that passes MINUTES of this "
                         "piece (a STOP file in the run folder does the same)")
    ta.set_defaults(func=cmd_train_anchor)

    cu = add("curve", "draw the learning curve of an anchor run folder (--run-dir)",
             "Draw curve.png of a `counterplay train-anchor --run-dir` folder from its curve.csv: held-out goal rate "
             "per style, the normal style's failure classes, the critic's explained variance.")
    cu.add_argument("run_dir", metavar="RUN_DIR", help="the run folder")
    cu.add_argument("--out", default=None, metavar="PNG", help="image to write (default: RUN_DIR/curve.png)")
    cu.set_defaults(func=cmd_curve)

    oc = add("outcomes", "self-play outcome rates of a checkpoint on held-out tasks",
             "Self-play outcome rates (goal, collision, off-road, timeout) of a checkpoint on held-out "
             "procedural tasks: every controllable agent driven by the policy under one condition. "
             "Prints them and writes them as JSON.")
    oc.add_argument("--model", default=DEFAULT_ANCHOR, metavar="ZIP",
                    help="checkpoint (SB3 .zip, CounterPlay, BC .pt), or 'expert' for the --teacher")
    oc.add_argument("--teacher", default="tracking", choices=TEACHERS,
                    help="the expert of --model expert: tracking (cpsim.expert.TrackingExpert), "
                         "reactive (cpsim.expert.ReactiveExpert), reactive-v1 ... reactive-v7 (its versioned styles, "
                         "cpsim.expert.REACTIVE_STYLE_V*)")
    oc.add_argument("--dynamics", default="jerk", choices=["jerk", "classic"],
                    help="dynamics of the simulator for --model expert")
    oc.add_argument("--tasks", type=_positive_int, default=256, metavar="N", help="held-out tasks")
    oc.add_argument("--max-agents", type=_positive_int, default=8, metavar="A", help="agent slots per world")
    oc.add_argument("--condition", type=_condition, default="normal", metavar="PROFILE",
                    help="condition of every agent: a profile (aggressive, normal-aggressive, normal, "
                         "cautious-normal, cautious) or 10 comma-separated raw values")
    oc.add_argument("--out", default="runs/outcomes.json", metavar="JSON", help="where to write the rates")
    oc.add_argument("--threads", type=_positive_int, default=None, help="torch threads (default: torch's)")
    oc.set_defaults(func=cmd_outcomes)

    se = add("searches", "list the searches a CounterPlay run kept; draw one",
             "List the searches a CounterPlay run kept beside its checkpoint, or draw one of them.")
    se.add_argument("--model", default="runs/counterplay/counterplay.zip", metavar="ZIP",
                    help="a CounterPlay checkpoint (its .searches.npz beside it is read) or a search file")
    se.add_argument("--show", type=_non_negative_int, default=None, metavar="K",
                    help="draw search K of the table (default: list them)")
    se.add_argument("--out", default=None, help="figure (.png/.pdf/.svg) or animation (.gif/.mp4) of --show "
                                                "(default: search_K.png)")
    se.set_defaults(func=cmd_searches)

    po = add("pool", "generate and summarise a procedural scenario pool",
             "Generate a procedural scenario pool and print a summary per family.")
    po.add_argument("--n", type=_positive_int, default=60, help="scenarios")
    po.add_argument("--seed", type=_non_negative_int, default=0, help="first seed")
    po.add_argument("--families", nargs="*", default=None, metavar="FAMILY",
                    help="procedural families to draw from (default: all)")
    po.set_defaults(func=cmd_pool)

    add_commands(add)  # experiment, methods (cpalgo.experiments.command)
    add_compress_command(add)  # compress-anchor (cpalgo.anchor.compress)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command; usage errors print one line and raise ``SystemExit(2)`` (argparse's way)."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UsageError as exc:
        args.parser.error(str(exc))  # prints usage and "counterplay SUB-COMMAND: error: ...", exits 2
    return 2  # not reached: error() exits


if __name__ == "__main__":
    raise SystemExit(main())
