"""CounterPlay's commands: ``counterplay post-train`` (:func:`cpalgo.counterplay.post_train.post_train`)
and ``searches`` (list the searches a run kept; draw one). ``run``, the main job, lives
with the experiments (:mod:`cpalgo.experiments.command`).
"""

from __future__ import annotations

import argparse

from cpalgo.common.checks import UsageError, check_out_path
from cpalgo.common.checks import set_threads as _set_threads
from cpalgo.counterplay.post_train import post_train

__all__ = ["cmd_post_train", "cmd_searches"]


def cmd_post_train(args: argparse.Namespace) -> int:
    _set_threads(args.threads)
    post_train(args.anchor, args.config, args.out, timesteps=args.timesteps, seed=args.seed,
               eval_tasks=args.eval_tasks, progress=args.progress, verbose=args.verbose,
               tensorboard=args.tensorboard, worlds=args.worlds, scenarios=args.scenarios)
    return 0


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
