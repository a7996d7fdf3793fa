"""The anchor's commands: ``counterplay train-anchor`` (a DAgger warm start, TeacherPPO or
plain PPO to one checkpoint; or with ``--run-dir`` / ``--resume`` a resumable self-play run,
:mod:`cpalgo.anchor.selfplay`), ``curve`` (that run's learning curve), ``export-anchor``
(that run's latest checkpoint as a shippable anchor, :mod:`cpalgo.anchor.export`) and
``outcomes`` (self-play outcome rates of a checkpoint on held-out tasks,
:mod:`cpalgo.anchor.outcomes`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from cpalgo.common.checks import UsageError, brief, check_out_path, load_womd_option
from cpalgo.common.checks import set_threads as _set_threads
from cpalgo.common.recipe_setup import check_algorithm_arguments, make_env
from cpalgo.evaluate.held_out import held_out_outcomes, held_out_tasks
from cpalgo.recipes import DEFAULT_ANCHOR_CONFIG, DEFAULT_SELFPLAY_CONFIG, load_recipe, resolve_path

__all__ = ["cmd_train_anchor", "cmd_curve", "cmd_export_anchor", "cmd_outcomes"]


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    from cpalgo.evaluate.tables import write_text_atomic

    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(doc, indent=2, default=str) + "\n")


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
            train_anchor_run(args.resume, resume=True, stop_after_s=stop, command=command, changes=args.set,
                             workers=args.workers)
            return 0
        if args.set:
            raise UsageError("--set: only with --resume (a new run takes its settings from --config)")
        if args.config is None:
            args.config = load_recipe(DEFAULT_SELFPLAY_CONFIG).path
        settings = AnchorRunSettings(
            recipe=args.config, seed=args.seed, timesteps=args.timesteps or load_recipe(args.config).n_timesteps,
            segment_timesteps=args.segment, pool_size=args.pool_size, womd_dir=args.add_womd,
            eval_tasks=args.eval_tasks, threads=args.threads, workers=args.workers or 1)
        train_anchor_run(args.run_dir, settings, stop_after_s=stop, command=command)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return 0


def cmd_curve(args: argparse.Namespace) -> int:
    from cpalgo.anchor.selfplay import curve_rise, curve_table, plot_curve, read_curve

    try:
        path = plot_curve(args.run_dir, args.out)
        rows = read_curve(args.run_dir)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.table:
        print(curve_table(rows, args.table))
    last = rows[-1]
    # a running piece writes a segment's row before its worker has evaluated it
    evaluated = [r for r in rows if "normal_goal" in r]
    held_out = (f"held-out goal aggressive / normal / cautious {evaluated[-1]['aggressive_goal']:.1%} / "
                f"{evaluated[-1]['normal_goal']:.1%} / {evaluated[-1]['cautious_goal']:.1%} "
                f"at {evaluated[-1]['timesteps'] / 1e6:.1f}M") if evaluated else "no held-out evaluation yet"
    print(f"{path}: {len(rows)} points, last at {last['timesteps'] / 1e6:.1f}M transitions "
          f"({last['wall_s'] / 3600:.2f} h): {held_out}")
    try:
        rise = curve_rise(rows)
    except ValueError as exc:  # too short a run for the plateau test
        print(f"plateau test: {exc}")
    else:
        print(f"plateau test: over the last third ({rise['start'] / 1e6:.1f}M to {rise['end'] / 1e6:.1f}M, "
              f"{rise['points']} points) the normal goal rate's fitted line rose {100 * rise['rise']:+.1f} points "
              f"(first / last quarter of the points {rise['first']:.1%} / {rise['last']:.1%})")
    return 0


def cmd_export_anchor(args: argparse.Namespace) -> int:
    from cpalgo.anchor.export import export_anchor

    check_out_path(args.out, "--out", folder=False)
    if args.json is not None:
        check_out_path(args.json, "--json", folder=False)
    _set_threads(args.threads)
    try:
        record = export_anchor(args.run_dir, args.out, args.json)
    except ValueError as exc:
        # the function names its arguments as Python does; the command line spells them so
        message = str(exc)
        for name, option in (("run_dir:", "RUN_DIR:"), ("out:", "--out:"), ("json_path:", "--json:")):
            if message.startswith(name):
                message = option + message[len(name):]
                break
        raise UsageError(message) from None
    source, anchor, curve = record["source"], record["anchor"], record["curve"]
    evaluated = "evaluated" if curve["last_row_evaluated"] else "not yet evaluated (see the record's curve rows)"
    print(f"{anchor['path']}: {anchor['bytes'] / 1e6:.2f} MB (the run's checkpoint {source['bytes'] / 1e6:.2f} MB), "
          f"{record['num_timesteps']:,} transitions, {record['segments']} segments, "
          f"{record['training_wall_s'] / 3600:.2f} h of training; its segment is {evaluated}")
    if args.json is not None:
        print(f"record written to {args.json}")
    return 0


def cmd_train_anchor(args: argparse.Namespace) -> int:
    if args.run_dir or args.resume:
        return _train_anchor_run(args)
    if args.set:
        raise UsageError("--set: only with --resume (it changes a resumable run's PPO settings)")
    if args.workers is not None:
        raise UsageError("--workers: only with --run-dir / --resume (data-parallel self-play runs)")
    _set_threads(args.threads)

    from cpalgo.checkpoint import AtomicCheckpointCallback, save_model_atomic

    if (args.teacher_style_pairs or args.style_pair_coef is not None or args.style_pair_focus) \
            and not args.teacher_coef > 0:
        raise UsageError("--teacher-style-pairs / --style-pair-coef / --style-pair-focus: need --teacher-coef > 0 "
                         "(TeacherPPO)")
    if args.style_pair_focus and not args.teacher_style_pairs:
        raise UsageError("--style-pair-focus: needs --teacher-style-pairs K > 0")
    recipe = load_recipe(args.config or DEFAULT_ANCHOR_CONFIG)
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
    env = make_env(recipe, args.seed, **overrides)
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
            raise UsageError(f"--init: {args.init} does not match the recipe's policy ({brief(exc)})") from None
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
    rates = held_out_outcomes(model, args.eval_tasks, recipe.env_kwargs.get("max_agents", 8))
    report = {"command": " ".join(sys.argv), "timesteps": int(model.num_timesteps), "wall_s": round(wall, 1),
              "normal_condition_outcomes": rates.as_dict()}
    if imitation:
        report["imitation_rounds"] = imitation
    _write_json(Path(str(out.with_suffix("")) + ".json"), report)
    print(f"anchor saved to {out} after {model.num_timesteps} steps in {wall:.0f} s")
    print(f"held-out outcomes under the normal condition: {rates}")
    return 0


def cmd_outcomes(args: argparse.Namespace) -> int:
    _set_threads(args.threads)
    check_out_path(args.out, "--out", folder=False)
    if args.model == "expert":  # an imitation teacher
        from cpalgo.anchor.outcomes import expert_outcomes

        rates = expert_outcomes(held_out_tasks(args.tasks), condition=args.condition, max_agents=args.max_agents,
                                config={"dynamics": args.dynamics}, teacher=args.teacher)
    else:
        from cpalgo.evaluate.runner import load_model

        path = resolve_path(args.model)
        try:
            model = load_model(path, "--model")
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        rates = held_out_outcomes(model, args.tasks, args.max_agents, args.condition)
    print(rates)
    out = Path(args.out)
    extra = {"teacher": args.teacher} if args.model == "expert" else {}
    _write_json(out, {"model": args.model if args.model == "expert" else path, **extra, "condition": args.condition,
                      "tasks": args.tasks, "max_agents": args.max_agents, "outcomes": rates.as_dict()})
    print(f"written to {out}")
    return 0
