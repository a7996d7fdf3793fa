"""Where an ego policy fails in the evaluator: near-miss timeouts and off-road in turns.

    python docs/results/anchor_failures/anatomy.py --policy zoo/anchor.zip --n 50 --deploy normal

For every task-regime of the evaluator (procedural pool, both splits, all 8 regimes, co-players
as the evaluator's default) it records the ego's episode and prints, per split and outcome:
the share of rows, and the ego's closest approach to its goal (a timeout that came within a few
metres is a near miss of the 2 m evaluation radius). For off-road rows it reports whether the
ego's logged route turns (> 45 deg between its first and last logged heading), how far the ego
had turned when it left the road, and its speed then against the logged speed at that step.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from cpalgo.evaluate import runner as R

OUTCOMES = ("goal", "timeout", "offroad", "at_fault_collision", "non_at_fault_collision")


def _turn_deg(h0: float, h1: float) -> float:
    return float(abs(np.degrees(np.angle(np.exp(1j * (h1 - h0))))))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", default="zoo/anchor.zip")
    p.add_argument("--traffic-policy", default="zoo/anchor.zip")
    p.add_argument("--n", type=int, default=50)
    p.add_argument("--deploy", default="normal")
    args = p.parse_args()
    tasks = R.make_tasks("procedural", "both", args.n, seed=0)
    ev = R.Evaluator(tasks, R.REGIMES, traffic_policy=args.traffic_policy,
                     config=R.EvalConfig(deploy_condition=args.deploy, progress=False))
    ev.config = dataclasses.replace(ev.config, record=tuple(range(ev.num_rows)))
    res = ev.run(args.policy)
    c, tr = res.columns, res.trajectories
    print(f"policy {args.policy}, deploy {args.deploy}, {args.n} tasks per split, {len(ev.regimes)} regimes")
    for split in ("interactive", "random"):
        rows = np.flatnonzero(c["split"] == split)
        dmin = np.empty(rows.size)
        for j, r in enumerate(rows):
            alive = tr[r]["alive"][0].astype(bool)
            dmin[j] = np.linalg.norm(tr[r]["xy"][0][alive] - tr[r]["goal_xy"], axis=-1).min()
        print(f"\n{split}: outcome, share of task-regimes, ego's closest approach to its goal")
        for name in OUTCOMES:
            m = c[name][rows].astype(bool)
            if m.any():
                d = dmin[m]
                print(f"  {name:24s} {100 * m.mean():5.1f}%  median {np.median(d):5.1f} m   "
                      f"< 4 m {100 * np.mean(d < 4):3.0f}%   < 8 m {100 * np.mean(d < 8):3.0f}%")
        off = rows[c["offroad"][rows].astype(bool)]
        if not off.size:
            continue
        turning, progress, v_ego, v_log = [], [], [], []
        for r in off:
            sc = ev.scenarios[int(ev.items["scenario"][r])]
            e = sc.ego_index
            valid = sc.log_valid[e].astype(bool)
            lh = sc.log_heading[e][valid]
            log_turn = _turn_deg(lh[0], lh[-1])
            alive = tr[r]["alive"][0].astype(bool)
            h = tr[r]["heading"][0][alive]
            t_end = int(alive.sum()) - 1
            turning.append(log_turn > 45.0)
            progress.append(_turn_deg(h[0], h[-1]) / max(log_turn, 1e-6))
            v_ego.append(abs(float(tr[r]["speed"][0][t_end])))
            speeds = np.linalg.norm(sc.log_velocity[e], axis=-1)
            v_log.append(float(speeds[min(t_end, speeds.size - 1)]))
        turning = np.array(turning)
        print(f"  off-road: {100 * turning.mean():.0f}% on routes that turn > 45 deg; there the ego had turned "
              f"{100 * np.median(np.array(progress)[turning]) if turning.any() else float('nan'):.0f}% "
              f"(median) of the route's turn when it left the road, at {np.median(np.array(v_ego)[turning]) if turning.any() else float('nan'):.1f} m/s "
              f"(logged speed at that step {np.median(np.array(v_log)[turning]) if turning.any() else float('nan'):.1f} m/s); "
              f"{len(set(c['scenario_id'][off]))} distinct tasks over {off.size} task-regimes")


if __name__ == "__main__":
    main()
