"""The ``counterplay`` parser and :func:`main`: sub-commands, options, help texts and
argument types. The commands themselves live in :mod:`cpalgo.cli.anchor`,
:mod:`cpalgo.cli.post`, :mod:`cpalgo.cli.scenarios`, :mod:`cpalgo.experiments.command` and
:mod:`cpalgo.anchor.compress`.
"""

from __future__ import annotations

import argparse
import math
import os
from typing import Sequence

from cpalgo.cli.anchor import cmd_curve, cmd_export_anchor, cmd_outcomes, cmd_train_anchor
from cpalgo.cli.post import cmd_post_train, cmd_searches
from cpalgo.cli.scenarios import cmd_pool
from cpalgo.common.checks import UsageError
from cpalgo.common.checks import non_negative_int as _non_negative_int
from cpalgo.common.checks import positive_int as _positive_int
from cpalgo.counterplay.post_train import DEFAULT_ANCHOR, DEFAULT_POST_CONFIG
from cpalgo.recipes import DEFAULT_ANCHOR_CONFIG, DEFAULT_SELFPLAY_CONFIG, load_recipe, resolve_path

__all__ = ["TEACHERS", "DEFAULT_ANCHOR_CONFIG", "DEFAULT_SELFPLAY_CONFIG", "build_parser", "main"]


#: Teacher names of ``--teacher`` (cpsim.expert.EXPERTS; kept here so the parser imports no Warp).
TEACHERS: tuple[str, ...] = ("tracking", "reactive", "reactive-v2", "reactive-v1", "reactive-v4", "reactive-v5",
                             "reactive-v6", "reactive-v7")


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
              f"Post-train a self-play anchor (--anchor, the shipped {DEFAULT_ANCHOR} by default) with "
              f"PPO-Continue and with CounterPlay at the same budget and seed on the procedural training pool "
              f"(--config, {DEFAULT_POST_CONFIG} by default), evaluate the anchor and both on the same held-out tasks "
              "(both splits, all traffic regimes: score, completion, at-fault collisions, timeouts, "
              "failure repair), and write the checkpoints, tables and a summary. --eval-tasks counts "
              "tasks per split.")
    common(run)
    run.add_argument("--anchor", type=_existing_file, default=DEFAULT_ANCHOR, metavar="ZIP",
                     help="anchor checkpoint both methods start from (they build its network)")
    run.add_argument("--config", type=_recipe_file, default=DEFAULT_POST_CONFIG, metavar="YAML",
                     help="zoo YAML recipe: PPO and CounterPlay settings and the training env "
                          "(zoo/counterplay_selfplay.yml for the self-play anchor)")
    post_options(run, "folder for the grid: runs/<method>/seed0/model.zip, results.csv, tables.md, "
                      "summary.md, summary.json and plots (a rerun resumes what is there)",
                 "B_post of each method: every agent transition, main or branch, counts, and both methods "
                 "stop at N (default: the recipe's n_timesteps)")
    from cpalgo.anchor.compress import add_command as add_compress_command
    from cpalgo.experiments.command import add_commands, main_job_defaults

    run.set_defaults(**main_job_defaults())

    pt = add("post-train", "CounterPlay post-training of an anchor checkpoint",
             "CounterPlay post-training of an anchor checkpoint with a zoo YAML recipe.")
    common(pt)
    pt.add_argument("--anchor", type=_existing_file, default=DEFAULT_ANCHOR, metavar="ZIP",
                    help="anchor checkpoint (its network is read from it; the recipe must fit its env)")
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
    ta.add_argument("--config", type=_recipe_file, default=None, metavar="YAML",
                    help=f"zoo YAML recipe (default: {DEFAULT_SELFPLAY_CONFIG} with --run-dir, the self-play "
                         f"anchor's; {DEFAULT_ANCHOR_CONFIG} otherwise, the teacher-imitation anchor's)")
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
    ta.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="with --resume: change a setting from this piece on: PPO (learning_rate, ent_coef, vf_coef, gamma, gae_lambda, "
                         "clip_range, max_grad_norm, n_epochs; schedules as in a recipe, e.g. "
                         "learning_rate=cosine(3e-3)), env (timeout_terminal=true|false, eval_task_share=S) or "
                         "threads=N or workers=N; recorded in the run's run.json and kept by later pieces; repeatable")
    ta.add_argument("--segment", type=_positive_int, default=10_000_000, metavar="N",
                    help="with --run-dir: transitions between checkpoints, curve points and pool draws")
    ta.add_argument("--pool-size", type=_positive_int, default=512, metavar="N",
                    help="with --run-dir: procedural training scenes drawn for every segment")
    ta.add_argument("--workers", type=_positive_int, default=None, metavar="N",
                    help="with --run-dir: N data-parallel training processes (each steps worlds / N of the "
                         "recipe's worlds, minibatches of batch_size / N, gradients averaged before every step; "
                         "one torch thread each unless --threads); must divide the worlds and batch_size. "
                         "Recorded in run.json: --resume uses the run's count (default 1; --set workers=N changes it)")
    ta.add_argument("--stop-after", type=float, default=None, metavar="MINUTES",
                    help="with --run-dir / --resume: stop cleanly after the segment that passes MINUTES of this "
                         "piece (a STOP file in the run folder does the same)")
    ta.set_defaults(func=cmd_train_anchor)

    cu = add("curve", "draw the learning curve of an anchor run folder (--run-dir)",
             "Draw curve.png of a `counterplay train-anchor --run-dir` folder from its curve.csv: held-out goal rate "
             "per style, the normal style's failure classes, the critic's explained variance.")
    cu.add_argument("run_dir", metavar="RUN_DIR", help="the run folder")
    cu.add_argument("--out", default=None, metavar="PNG", help="image to write (default: RUN_DIR/curve.png)")
    cu.add_argument("--table", type=_positive_int, default=None, metavar="EVERY",
                    help="also print the curve as a markdown table: every EVERY-th segment and the last")
    cu.set_defaults(func=cmd_curve)

    ex = add("export-anchor", "write an anchor run's latest checkpoint as a shippable anchor",
             "Write the latest checkpoint of a `counterplay train-anchor --run-dir` folder as an anchor to ship: "
             "the same weights and settings, without Adam's moments and the state only a resumed piece needs "
             "(RNG states, curve rows, the budget's per-generation log; cpalgo.anchor.export). --json also "
             "writes where it came from: recipe, settings and changes, commands, transitions, segments, "
             "training wall time, network, machine, the file's sha256 and the last held-out curve rows.")
    ex.add_argument("run_dir", metavar="RUN_DIR", help="the run folder (checkpoint.zip, run.json)")
    ex.add_argument("--out", required=True, metavar="ZIP", help="anchor file to write (replaced atomically)")
    ex.add_argument("--json", default=None, metavar="JSON", help="also write the provenance record here")
    ex.add_argument("--threads", type=_positive_int, default=None, help="torch threads (default: torch's)")
    ex.set_defaults(func=cmd_export_anchor)

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
