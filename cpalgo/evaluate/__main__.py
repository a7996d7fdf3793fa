"""Command line: ``python -m cpalgo.evaluate``.

Example::

    python -m cpalgo.evaluate --policy anchor=zoo/anchor.zip --policy counterplay=runs/cp.zip \\
        --traffic-policy zoo/anchor.zip --split both --n 50 --deploy normal --out results/eval

``--policy`` takes ``PATH`` or ``LABEL=PATH`` (repeat it; the same label on several
checkpoints aggregates them as seeds: mean and std). ``PATH`` may also be a built-in
controller: ``expert`` (log replay) or ``idm``, or an imitation teacher of
``cpsim.expert`` (``reactive``, ``tracking``) driving the ego under the deployment
condition. The simulator takes the dynamics of the learned policies (their action sets:
12 jerk, 91 classic; every checkpoint and ``--dynamics`` must agree). Everything is validated before the first simulator step; on a bad input the
command exits with status 2 and a message, and no result folder is written. The result folder is written atomically at the end.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Sequence

import numpy as np


def _parse_policy(spec: str) -> tuple[str | None, str]:
    if "=" in spec:
        label, path = spec.split("=", 1)
        if not label:
            raise ValueError(f"--policy {spec!r}: empty label before '='")
        return label, path
    return None, spec


def _parse_regimes(values: Sequence[str]) -> list[str]:
    from cpalgo.evaluate.runner import REGIMES, resolve_regime

    names = [v for item in values for v in item.split(",") if v]
    if not names or names == ["all"]:
        return list(REGIMES)
    return [resolve_regime(n) for n in names]


def _parse_deploy(spec: str) -> str | tuple[float, ...]:
    from cpsim.conditions import resolve_condition

    if "," in spec:
        try:
            vec = tuple(float(x) for x in spec.split(","))
        except ValueError:
            raise ValueError(f"--deploy: {spec!r} is neither a profile name nor 10 comma-separated numbers") from None
        resolve_condition(np.asarray(vec, np.float32), "--deploy")
        return vec
    resolve_condition(spec, "--deploy")
    return spec


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m cpalgo.evaluate",
                                description="BehaviorBench-style evaluation over traffic regimes.",
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--policy", action="append", required=True, metavar="[LABEL=]PATH",
                   help="ego policy checkpoint (.zip SB3 / CounterPlay, .pt BC), a built-in controller "
                        "('expert' = log replay, 'idm') or an imitation teacher ('reactive', 'tracking'); repeatable")
    p.add_argument("--regimes", nargs="+", default=["all"],
                   help="traffic regimes (space or comma separated; default all eight: "
                        "idm selfplay bc replay aggressive normal cautious mix)")
    p.add_argument("--split", default="both", help="interactive, random or both")
    p.add_argument("--n", type=int, default=50, help="tasks per split")
    p.add_argument("--pool", default="procedural",
                   help="'procedural' (eval_pool) or a folder of WOMD .json / .json.gz / .npz files "
                        "(one task per tracks_to_predict vehicle)")
    p.add_argument("--pool-size", type=int, default=None, help="procedural pool size (default 4 n)")
    p.add_argument("--deploy", default="normal",
                   help="ego condition: profile (cautious, cautious-normal, normal, normal-aggressive/halfway, "
                        "aggressive) or 10 comma-separated raw values; it sets the style fields only, "
                        "the goal test is the same for every condition (2 m, no speed limit)")
    p.add_argument("--traffic-policy", default=None,
                   help="co-player checkpoint for aggressive / normal / cautious / mix "
                        "(default: the shipped anchor of the dynamics, zoo/anchor.zip in classic, "
                        "zoo/anchor_imitation.zip in jerk)")
    p.add_argument("--bc-policy", default=None, help="BC traffic model for 'bc' (default zoo/bc_traffic.pt)")
    p.add_argument("--ppo-policy", default=None,
                   help="self-play PPO co-player checkpoint for 'selfplay' (default: the shipped one of the "
                        "dynamics, zoo/ppo_traffic_classic.zip in classic, zoo/ppo_traffic.zip in jerk; "
                        "without it the --traffic-policy under p_train conditions)")
    p.add_argument("--dynamics", choices=("jerk", "classic"), default=None,
                   help="simulator dynamics (default: that of the learned policies, read from their action "
                        "sets: 12 actions jerk, 91 classic; every --policy, --traffic-policy and --ppo-policy "
                        "checkpoint must agree, and with this option when given)")
    p.add_argument("--reference", default=None, help="label of the outcome analysis' reference (default first)")
    p.add_argument("--out", required=True, help="results folder (replaced atomically)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-worlds", type=int, default=256, help="task-regimes simulated at once")
    p.add_argument("--max-agents", type=int, default=None)
    p.add_argument("--coplayers", choices=("vehicles", "controllable"), default="vehicles",
                   help="who follows the regime: every vehicle present at t0 (BehaviorBench, default) "
                        "or only controllable ones (parked vehicles replay their logs)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--record", type=int, default=3,
                   help="record the first K tasks of each split and regime for the scene figure")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--no-progress", action="store_true")
    return p


def run(argv: Sequence[str] | None = None) -> dict:
    """Parse, validate, evaluate and write; raises ``ValueError`` on bad input."""
    from cpalgo.evaluate import runner as R
    from cpalgo.evaluate import tables as TB

    args = build_parser().parse_args(argv)
    # ---- validate everything cheap first (no simulator, no file written)
    regimes = _parse_regimes(args.regimes)
    R.resolve_split(args.split)
    deploy = _parse_deploy(args.deploy)
    if args.n < 1:
        raise ValueError(f"--n: must be >= 1, got {args.n}")
    if args.seed < 0:
        raise ValueError(f"--seed: must be >= 0, got {args.seed}")
    if args.pool_size is not None and args.pool_size < args.n:
        raise ValueError(f"--pool-size: must be >= --n ({args.n}: each split takes --n tasks of the pool), "
                         f"got {args.pool_size}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out: {out} exists and is not a folder")
    specs = [_parse_policy(s) for s in args.policy]
    egos = [R.as_ego_policy(path, label) for label, path in specs]
    labels = [e.label for e in egos]
    if args.reference is not None and args.reference not in labels:
        raise ValueError(f"--reference: {args.reference!r} is not one of the policy labels {labels}")
    # the learned policies choose the simulator's dynamics (their action sets); all must agree
    traffic = None if args.traffic_policy is None else R.load_model(args.traffic_policy, "--traffic-policy")
    ppo = None if args.ppo_policy is None or "selfplay" not in regimes else R.load_model(args.ppo_policy,
                                                                                       "--ppo-policy")
    named = [(f"--policy {e.checkpoint or e.label!r}", e) for e in egos]
    R.resolve_dynamics([*named, ("--traffic-policy", traffic), ("--ppo-policy", ppo)], args.dynamics, "--dynamics")
    tasks = R.make_tasks(args.pool, args.split, args.n, seed=args.seed, pool_size=args.pool_size)
    cfg = R.EvalConfig(deploy_condition=deploy, max_worlds=args.max_worlds, max_agents=args.max_agents,
                       seed=args.seed, device=args.device, progress=not args.no_progress,
                       coplayers=args.coplayers)
    ev = R.Evaluator(tasks, regimes, traffic_policy=traffic, bc_policy=args.bc_policy,
                     ppo_policy=ppo if ppo is not None else args.ppo_policy, config=cfg,
                     policies=dict(named), dynamics=args.dynamics)
    for e in egos:  # observation layout of every checkpoint, before any run
        if e.controller == R._POLICY:
            R.check_obs_size(e, ev.obs_size, f"--policy {e.checkpoint or e.label!r}")
    if args.record > 0:
        rows = np.flatnonzero(ev.items["task"] < args.record)
        ev.config = dataclasses.replace(ev.config, record=tuple(int(r) for r in rows))
    # ---- evaluate and write
    results = [ev.run(e) for e in egos]
    defaults = {argument: str(path) for argument, path in ev.default_paths.items()}  # co-players not given
    extra = {
        "command": "python -m cpalgo.evaluate " + " ".join(argv if argv is not None else sys.argv[1:]),
        "pool": str(args.pool), "split": args.split, "n": args.n, "seed": args.seed,
        "deploy": deploy if isinstance(deploy, str) else list(deploy), "regimes": regimes,
        "traffic_policy": args.traffic_policy or defaults.get("traffic_policy"),
        "bc_policy": args.bc_policy, "coplayers": args.coplayers,
        "ppo_policy": args.ppo_policy or defaults.get("ppo_policy"),
        "dynamics": ev.dynamics,
        "dynamics_from": {None: "default", "dynamics": "--dynamics"}.get(ev.dynamics_source, ev.dynamics_source),
        **({"notes": dict(ev.notes)} if ev.notes else {}),
        "policies": [{"label": r.label, "checkpoint": r.checkpoint, **r.meta} for r in results],
    }
    scenarios = {t.scenario_id: t.scenario for t in tasks}
    summary = TB.write_results(out, results, reference=args.reference, plots=not args.no_plots,
                               scenarios=scenarios, extra=extra)
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    try:
        summary = run(argv)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from cpalgo.evaluate import tables as TB

    print(TB.markdown_tables(summary, TB.TABLE_METRICS[:2]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
