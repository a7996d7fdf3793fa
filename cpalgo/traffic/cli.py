"""``python -m cpalgo.traffic`` (also ``python -m cpalgo.bc``): train the behaviour-cloning
traffic model (:mod:`cpalgo.traffic.bc`) and, with ``--report``, measure it before and
after (:func:`cpalgo.traffic.measure.measure_traffic`). The command of the shipped model
is in :mod:`cpalgo.traffic.bc`'s docstring."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import torch as th

from cpalgo.traffic.bc import COLLECT_MODES, HEADS, BCPolicy, DaggerConfig, TrainConfig, collect, dagger, train
from cpalgo.traffic.bc import __doc__ as _BC_DOC
from cpalgo.traffic.measure import measure_traffic
from cpsim.atomic import write_text_atomic

__all__ = ["main"]


def _load_pool(p: argparse.ArgumentParser, pool: str, n: int, seed: int, flag: str) -> list[Any]:
    if pool == "procedural":
        from cpsim.scenario import train_pool

        return list(train_pool(n, seed))
    if not Path(pool).is_dir():
        p.error(f"{flag}: {pool!r} is neither 'procedural' nor a folder")
    from cpsim.scenario import load_dir

    loaded = load_dir(pool)
    return list(loaded[0] if isinstance(loaded, tuple) else loaded)[:n]


def _floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m cpalgo.traffic", description=_BC_DOC.split("\n\n")[0])
    p.add_argument("--out", required=True, help="checkpoint path (.pt), written atomically")
    p.add_argument("--scenarios", type=int, default=200, help="training-pool scenarios (procedural)")
    p.add_argument("--pool", default="procedural", help="'procedural' or a folder of WOMD JSON/.npz")
    p.add_argument("--interactive", type=int, default=0, metavar="N",
                   help="add the N most interactive procedural scenes (cpsim.scenario.interactive_split, "
                        "BehaviorBench's score) of a further training pool of 4 N (seed + 1)")
    p.add_argument("--extra-pool", default=None,
                   help="a folder of WOMD scenes added (all of them) to the --pool scenarios")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch threads (small batches: 1 is fastest on a shared CPU)")
    p.add_argument("--worlds", type=int, default=32)
    p.add_argument("--max-agents", type=int, default=32,
                   help="agent slots per world (DAgger: at most; each pool gets the most agents present at t0)")
    p.add_argument("--epochs", type=int, default=15, help="epochs (without --dagger)")
    p.add_argument("--hidden", type=int, nargs="+", default=[128, 128])
    p.add_argument("--head", choices=HEADS, default="actions",
                   help="actions: classify the label; targets: regress the tracking expert's target "
                        "accelerations (--dagger only)")
    p.add_argument("--batch-size", type=int, default=512)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--weight-decay", type=float, default=1e-5)
    p.add_argument("--mode", choices=COLLECT_MODES, default="both",
                   help="replay: log-replay observations only; track: noisy log tracking; both")
    p.add_argument("--noise", type=float, default=0.2,
                   help="random-action probability when tracking (DAgger: of the expert in round 0)")
    p.add_argument("--lookahead", type=int, default=5, help="label lookahead, steps")
    g = p.add_argument_group("DAgger against the tracking expert (replaces --mode/--lookahead labels)")
    g.add_argument("--dagger", type=_floats, default=None, metavar="B0,B1,...",
                   help="one expert share beta per round, starting with 1 (e.g. 1,0.5,0,0)")
    g.add_argument("--first-epochs", type=int, default=6, help="epochs after round 0 (fresh model)")
    g.add_argument("--round-epochs", type=int, default=3, help="epochs after each later round (warm start)")
    g.add_argument("--ego-replay", type=float, default=0.5, help="share of worlds whose slot 0 replays its log")
    g.add_argument("--keep", type=float, default=1.0, help="share of visited states kept as samples")
    g.add_argument("--coplayers", choices=("controllable", "vehicles"), default="controllable",
                   help="who the model drives (cpsim.envs.regimes rule; the evaluator's default: controllable)")
    r = p.add_argument_group("report: the expert-replay ego under bc traffic, before and after")
    r.add_argument("--report", default=None, help="JSON report path (command, time, harm and at-fault)")
    r.add_argument("--baseline", default=None,
                   help="model measured as 'before' (default: the shipped model, read before --out is written)")
    r.add_argument("--eval-n", type=int, default=50, help="tasks per split of the procedural evaluation pool")
    r.add_argument("--eval-womd", default=None, help="also measure on this WOMD folder (e.g. the valid split)")
    r.add_argument("--eval-womd-n", type=int, default=50, help="tasks per split on --eval-womd")
    args = p.parse_args(argv)
    if not str(args.out).endswith(".pt"):
        p.error("--out must end in .pt")
    if args.scenarios < 2:
        p.error("--scenarios must be >= 2")
    if args.dagger is not None:
        try:
            DaggerConfig(betas=args.dagger)
        except ValueError as exc:
            p.error(f"--dagger: {exc}")
    baseline = None
    if args.report:
        from cpalgo.evaluate.runner import DEFAULT_BC_PATH

        base_path = args.baseline or DEFAULT_BC_PATH
        baseline = BCPolicy.load(base_path) if Path(base_path).is_file() else None
    if args.threads < 1:
        p.error("--threads must be >= 1")
    th.set_num_threads(args.threads)
    command = "python -m cpalgo.traffic " + " ".join(argv if argv is not None else sys.argv[1:])
    t0 = time.perf_counter()
    groups = [_load_pool(p, args.pool, args.scenarios, args.seed, "--pool")]
    if args.interactive < 0:
        p.error("--interactive must be >= 0")
    if args.interactive:
        from cpsim.scenario import interactive_split, train_pool

        groups[0] += list(interactive_split(list(train_pool(4 * args.interactive, args.seed + 1)), args.interactive))
    if args.extra_pool:
        groups.append(_load_pool(p, args.extra_pool, 10 ** 9, args.seed, "--extra-pool"))
    scenarios = [sc for g in groups for sc in g]
    from cpsim.config import SimConfig

    tc = TrainConfig(hidden=tuple(args.hidden), epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                     weight_decay=args.weight_decay, seed=args.seed, head=args.head)
    if args.head == "targets" and args.dagger is None:
        p.error("--head targets needs --dagger (the tracking expert's targets)")
    info = {"scenarios": len(scenarios), "pool": args.pool, "extra_pool": args.extra_pool, "seed": args.seed,
            "command": command}
    if args.dagger is not None:
        dc = DaggerConfig(betas=args.dagger, first_epochs=args.first_epochs, round_epochs=args.round_epochs,
                          noise=args.noise, ego_replay=args.ego_replay, keep=args.keep, num_worlds=args.worlds,
                          max_agents=args.max_agents, coplayers=args.coplayers)
        # per-round checkpoints go next to --out, which is written once at the end (it may be
        # the shipped model that evaluations read meanwhile)
        partial = Path(args.out).with_name(Path(args.out).stem + ".partial.pt")
        model, history = dagger(groups, dc, tc, seed=args.seed, log=True, checkpoint=partial, meta=info)
        metrics = {k: history[-1][k] for k in ("train_accuracy", "val_accuracy", "val_majority_accuracy")}
        metrics.update(info, train_seconds=time.perf_counter() - t0, dagger=history)
    else:
        data = collect(scenarios, args.worlds, args.max_agents, seed=args.seed, progress=True,
                       lookahead=args.lookahead, mode=args.mode, noise=args.noise)
        t1 = time.perf_counter()
        import cpsim

        probe = cpsim.Simulator(scenarios[:1], num_worlds=1, max_agents=args.max_agents)
        sl = probe.obs_layout.condition
        model, metrics = train(data, SimConfig().num_actions, (int(sl.start), int(sl.stop)), tc, log=True)
        metrics.update(info, collect_seconds=t1 - t0, train_seconds=time.perf_counter() - t1)
    model.meta = metrics
    path = model.save(args.out)
    if args.dagger is not None:
        partial.unlink(missing_ok=True)
    summary: dict[str, Any] = {"out": str(path), "bytes": path.stat().st_size, **metrics}
    if args.report:
        t2 = time.perf_counter()
        models = {"before": baseline, "after": model} if baseline is not None else {"after": model}
        report: dict[str, Any] = {
            "command": command, "model": str(path), "bytes": path.stat().st_size,
            "train_seconds": t2 - t0, "dagger": metrics.get("dagger"),
            "ego": "expert-replay", "metric_note": (
                "co_player_harm: other vehicles that collided or went off-road, per task; at_fault: share of "
                "tasks where the expert-replay ego has an at-fault collision; before: --baseline (default the "
                "model shipped before this run), after: this run's model, replay: the log-replay regime"),
            "procedural": {"pool": "procedural eval_pool", "n_per_split": args.eval_n,
                           **measure_traffic(models, "procedural", args.eval_n, args.seed)}}
        if args.eval_womd:
            report["womd"] = {"pool": args.eval_womd, "n_per_split": args.eval_womd_n,
                              "caveat": "log artefacts (parked cars touching road edges at step 1) count as "
                                        "co-player harm even under log replay; compare with the replay row",
                              **measure_traffic(models, args.eval_womd, args.eval_womd_n, args.seed)}
        report["eval_seconds"] = time.perf_counter() - t2
        report["seconds"] = time.perf_counter() - t0
        write_text_atomic(args.report, json.dumps(report, indent=2) + "\n")
        summary["report"] = {k: report[k] for k in ("procedural", "womd") if k in report}
    print(json.dumps(summary, indent=2, default=str))
    return 0
