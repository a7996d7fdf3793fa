"""Sub-commands of ``counterplay`` that live with the experiments: ``experiment``,
``methods`` and the main job ``run`` (registered by :func:`add_commands` from
:func:`cpalgo.cli.build_parser`)."""

from __future__ import annotations

import argparse
import sys
from typing import Any, Callable

__all__ = ["add_commands", "cmd_experiment", "cmd_methods", "cmd_main_job"]


def _usage_error(args: argparse.Namespace, message: str) -> None:
    """One ``error:`` line and exit status 2, as ``cpalgo.cli`` reports usage errors."""
    args.parser.error(message)


def cmd_methods(args: argparse.Namespace) -> int:
    from cpalgo.methods import describe_methods

    print(describe_methods())
    return 0


def cmd_experiment(args: argparse.Namespace) -> int:
    from cpalgo.experiments.grid import GridError
    from cpalgo.experiments.runner import run_experiment

    try:
        result = run_experiment(args.config, args.out, address=args.address, backend=args.backend,
                                progress=args.progress)
    except GridError as exc:
        _usage_error(args, str(exc))
        return 2
    except KeyboardInterrupt:  # finished runs and the last checkpoints stay; a rerun resumes
        print(f"\ninterrupted; run the same command again to resume from {args.out}", file=sys.stderr)
        return 130
    return 0 if result.ok else 1


def cmd_main_job(args: argparse.Namespace) -> int:
    """``counterplay run``: the main job (:mod:`cpalgo.experiments.mainjob`)."""
    from cpalgo.experiments.mainjob import run_main_job

    try:
        summary = run_main_job(anchor=args.anchor, config=args.config, out=args.out, budget=args.timesteps,
                               seed=args.seed, eval_tasks=args.eval_tasks, worlds=args.worlds,
                               torch_threads=args.threads or 1, progress=args.progress,
                               scenarios=getattr(args, "scenarios", None))
    except ValueError as exc:
        _usage_error(args, str(exc))
        return 2
    except KeyboardInterrupt:
        print(f"\ninterrupted; run the same command again to resume from {args.out}", file=sys.stderr)
        return 130
    print(summary["markdown"])
    print(f"written to {args.out} ({summary['wall_s'] / 60:.1f} min)")
    return 0


def add_commands(add: Callable[..., argparse.ArgumentParser]) -> None:
    """Add ``experiment`` and ``methods`` with ``cpalgo.cli``'s ``add(name, help, description)``."""
    ex = add("experiment", "run a grid of post-training methods x seeds and write the paper's tables",
             "Run every (method, seed) post-training of a grid file from one anchor at the same budget "
             "B_post, evaluate each on both splits under the grid's deployment conditions, and write "
             "results.csv, tables.md and plots into --out. Runs are Ray tasks when Ray is installed (extra "
             "[cluster]; --address joins a cluster), else they run one after another. Run it again with "
             "the same --out to resume: finished runs are skipped, killed runs continue from their last "
             "checkpoint.")
    ex.add_argument("--config", required=True, metavar="GRID.yml",
                    help="grid file (zoo/experiments/paper_small.yml is the paper at small scale)")
    ex.add_argument("--out", required=True, metavar="DIR", help="results folder (created; reused to resume)")
    ex.add_argument("--address", default=None, metavar="ADDR",
                    help="Ray cluster: 'auto' or 'ray://host:10001' (default: start Ray on this machine)")
    ex.add_argument("--backend", default="auto", choices=["auto", "ray", "sequential"],
                    help="auto: Ray when installed, else one run after another in this process")
    ex.add_argument("--no-progress", dest="progress", action="store_false", help="no progress lines")
    ex.set_defaults(func=cmd_experiment)

    me = add("methods", "list the post-training methods (one line each)",
             "List the registered post-training methods: name, table group and what it does.")
    me.set_defaults(func=cmd_methods)


def main_job_defaults() -> dict[str, Any]:
    """Defaults ``counterplay run`` takes over from ``post-train``'s options."""
    return {"func": cmd_main_job, "eval_tasks": 50}
