"""Where does a checkpoint's ego leave the road, and how far is that from the teacher's path?

Runs the evaluator's Interactive split (100 tasks, idm traffic, the checkpoint as the other
regimes' traffic) with the checkpoint and with the reactive teacher as ego under one
deployment condition, records every episode, and for each off-road episode of the checkpoint
prints: the distance to the goal and the speed at the off-road step, the heading change over
the second before it, and the distance from that point to the nearest point of the teacher's
path on the same task (and the teacher's speed there).

    python docs/results/pairs/offroad_probe.py runs/pairs2/P8.zip aggressive
"""
import collections
import dataclasses
import sys

import numpy as np

from cpalgo.evaluate import runner as R


def main(model: str, deploy: str, n: int = 100) -> None:
    tasks = R.make_tasks("procedural", "interactive", n, seed=0, pool_size=None)
    cfg = R.EvalConfig(deploy_condition=deploy, seed=0, progress=False)
    ev = R.Evaluator(tasks, ["idm"], traffic_policy=model, bc_policy=None, ppo_policy=None, config=cfg)
    ev.config = dataclasses.replace(ev.config, record=tuple(range(len(ev.items["task"]))))
    student = ev.run(R.as_ego_policy(model, "student"))
    teacher = ev.run(R.as_ego_policy("reactive", "teacher"))
    c = student.columns
    rows = np.flatnonzero(c["offroad"])
    stats = collections.defaultdict(list)
    for r in rows:
        a, b = student.trajectories[int(r)], teacher.trajectories[int(r)]
        xy = a["xy"][0]  # ego slot: (T+1, 2) m
        k = min(int(c["steps_alive"][r]), xy.shape[0] - 1)
        heading = np.unwrap(a["heading"][0, : k + 1])
        gap = np.linalg.norm(b["xy"][0] - xy[k], axis=1)
        j = int(np.argmin(gap))
        stats["goal distance at off-road (m)"].append(float(np.linalg.norm(xy[k] - a["goal_xy"])))
        stats["speed at off-road (m/s)"].append(float(a["speed"][0, k]))
        stats["heading change over the last 10 steps (rad)"].append(float(abs(heading[-1] - heading[max(0, k - 10)])))
        if teacher.columns["goal"][r]:  # a teacher stuck short of the point has no path there
            stats["distance to the teacher's path, tasks it completes (m)"].append(float(gap[j]))
            stats["teacher's speed there (m/s)"].append(float(b["speed"][0, j]))
    print(f"{model} under {deploy}: off-road {rows.size}/{c['offroad'].size} (teacher "
          f"{int(teacher.columns['offroad'].sum())}), goals {int(c['goal'].sum())} (teacher "
          f"{int(teacher.columns['goal'].sum())})")
    print("scenario kinds:", dict(collections.Counter(str(s).split("-")[0] for s in c["scenario_id"][rows])))
    for name, v in stats.items():
        print(f"  {name}: quartiles {np.round(np.percentile(v, [25, 50, 75]), 1).tolist()}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else "aggressive")
