"""Evaluation throughput: ``python -m cpalgo.evaluate.bench [--n N]``.

Measures task-regime evaluations per second of :class:`cpalgo.evaluate.runner.Evaluator`
(simulator construction and Warp module load excluded) for

1. the logged expert as the ego (no network) under ``replay`` and ``idm`` traffic, and
2. an untrained RecurrentPPO (SB3 default ``MlpLstmPolicy``) as the ego and as the
   co-player policy, with a BC traffic model, in all eight regimes.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from typing import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m cpalgo.evaluate.bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=25, help="tasks per split for the expert run")
    p.add_argument("--n-policy", type=int, default=10, help="tasks per split for the RecurrentPPO run")
    p.add_argument("--device", default="cpu")
    args = p.parse_args(argv)

    from cpalgo.evaluate import runner as R
    from cpalgo.traffic.bc import BCPolicy

    tasks = R.make_tasks("procedural", "both", args.n, seed=0)
    t = time.perf_counter()
    ev = R.Evaluator(tasks, ["replay", "idm"], config=R.EvalConfig(progress=False, device=args.device))
    build = time.perf_counter() - t
    r = ev.run("expert")
    print(f"expert ego, replay+idm: {r.num_rows} task-regimes, {r.meta['num_worlds']} worlds x "
          f"{r.meta['max_agents']} slots: {r.meta['seconds']:.2f} s -> "
          f"{r.meta['task_regimes_per_second']:.1f} task-regimes/s (build {build:.1f} s)")

    from sb3_contrib import RecurrentPPO

    from cpsim.envs.selfplay import SelfPlayVecEnv

    env = SelfPlayVecEnv([tasks[0].scenario], num_worlds=1, max_agents=4, device=args.device)
    model = RecurrentPPO("MlpLstmPolicy", env, seed=0, device="cpu")
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "policy.zip")
        model.save(path)
        lay = env.obs_layout
        bc = BCPolicy(lay.size, env.action_space.n, (256,), (lay.condition.start, lay.condition.stop))
        bc_path = bc.save(os.path.join(d, "bc.pt"))
        small = R.make_tasks("procedural", "both", args.n_policy, seed=0)
        ev = R.Evaluator(small, R.REGIMES, traffic_policy=path, bc_policy=bc_path,
                         config=R.EvalConfig(progress=False, device=args.device))
        r = ev.run(path)
    print(f"RecurrentPPO ego + co-players, 8 regimes: {r.num_rows} task-regimes, {r.meta['num_worlds']} "
          f"worlds x {r.meta['max_agents']} slots: {r.meta['seconds']:.2f} s -> "
          f"{r.meta['task_regimes_per_second']:.1f} task-regimes/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
