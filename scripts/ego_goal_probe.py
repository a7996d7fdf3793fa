"""How far a checkpoint's designated ego gets when its goal sits earlier or later on its log.

The procedural ego's goal is where its logged (rule-driver) drive was a few seconds before the
log ends (``cpsim.scenario.procedural.EGO_GOAL_SLACK``). This probe moves the goal of every
task's ego to its log position at step K (K = 90: the log's end, which leaves no time to
yield) and evaluates the ego, argmax actions under the normal profile, in one traffic regime,
with its co-players or alone (every other agent removed from the scene).

    python scripts/ego_goal_probe.py runs/anchor_selfplay/checkpoint.zip --steps 50 60 70 80 90

Prints one row per goal step, setting and split: completion, at-fault, off-road and timeout
rates (%) of the designated ego.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np


def moved_goal(task, step: int, alone: bool):
    """``task`` with its ego's goal at its log position at ``step``; ``alone``: the other
    agents removed (never valid)."""
    from cpalgo.evaluate.runner import Task

    s = task.scenario
    e = task.ego
    if not s.log_valid[e, step]:
        raise ValueError(f"--steps: the ego of {s.id} has no log position at step {step}")
    goal = s.goal_xy.copy()
    goal[e] = s.log_xy[e, step]
    valid = s.log_valid.copy()
    if alone:
        keep = np.zeros(valid.shape[0], bool)
        keep[e] = True
        valid[~keep] = False
    return Task(task.split, task.index, dataclasses.replace(s, goal_xy=goal, log_valid=valid))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint")
    p.add_argument("--steps", type=int, nargs="+", default=[50, 60, 70, 80, 90],
                   help="log steps (0-90) to put the ego's goal at")
    p.add_argument("--tasks", type=int, default=100, help="tasks per split (procedural, task set --seed)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--regime", default="normal", help="traffic regime of the co-players")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    if any(not 0 < k <= 90 for k in args.steps):
        raise SystemExit(f"--steps: log steps lie in 1..90, got {args.steps}")

    import torch

    from cpalgo.counterplay.algorithm import CounterPlay
    from cpalgo.evaluate.runner import evaluate, make_tasks

    torch.set_num_threads(args.threads)
    model = CounterPlay.load(args.checkpoint, device="cpu")
    tasks = make_tasks("procedural", "both", n=args.tasks, seed=args.seed)
    print("| goal at log step | co-players | split | completion | at-fault | off-road | timeout |")
    print("|---|---|---|---|---|---|---|")
    for step in args.steps:
        for alone in (False, True):
            res = evaluate(model, [moved_goal(t, step, alone) for t in tasks], regimes=(args.regime,),
                           deploy_condition="normal", traffic_policy=model, progress=False)
            c = res.columns
            for split in ("interactive", "random"):
                k = c["split"] == split
                rates = [100 * float(c[x][k].mean()) for x in ("goal", "at_fault_collision", "offroad", "timeout")]
                who = "none (alone)" if alone else args.regime
                print(f"| {step} | {who} | {split} | " + " | ".join(f"{r:.0f}" for r in rates) + " |", flush=True)


if __name__ == "__main__":
    main()
