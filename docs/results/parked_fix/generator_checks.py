"""The parked family's numbers in docs/results/README.md ("The parked family, corrected").

    python docs/results/parked_fix/generator_checks.py      # about 1 minute on one core

Prints, for parked seeds 0-39: how many ego logs reach their goal, how long the logged ego
yields to another agent (the driver's trace), how many slow below 2 m/s, the straight-line
distance from start to goal and the distance from the bypass lane's middle vertex to the
oncoming lane; then the share of controllable agents of train_pool(120) whose logs reach
their goals, per family, and the scenes of eval_pool(400, seed=0) the evaluator drops.
"""
from __future__ import annotations

from collections import Counter

import numpy as np

import cpsim.scenario.procedural as P
from cpsim.scenario import ego_log_reaches_goal, eval_pool, train_pool

_traces: dict = {}


def _traced_drive(lanes, levels, conflicts, plan, **kwargs):
    trace: list = []
    result = _drive(lanes, levels, conflicts, plan, trace=trace)
    _traces["last"] = trace
    return result


def _traced_clean(net, conflicts, plan, ego):
    out = _clean(net, conflicts, plan, ego)
    _traces["final"], _traces["ego"] = _traces["last"], out[2]
    return out


def _traced_once(*args):
    scene = _once(*args)
    _traces.setdefault("by_scene", {})[id(scene.scenario)] = (_traces["final"], _traces["ego"])
    return scene


def _bypass_separation(rng, net):
    _parked(rng, net)
    bypass = [i for i, level in enumerate(net.levels) if level == 0][-1]
    middle = net.lanes[bypass][len(net.lanes[bypass]) // 2]
    _traces.setdefault("separation", []).append(float(np.min(np.hypot(*(net.lanes[bypass + 1] - middle).T))))


_drive, _clean, _once, _parked = P.drive, P._drive_clean, P._build_once, P._family_parked
P.drive, P._drive_clean, P._build_once = _traced_drive, _traced_clean, _traced_once
P._BUILDERS["parked"] = _bypass_separation

reached, yields, slow, distance, separation = [], [], [], [], []
for seed in range(40):
    _traces["separation"] = []
    scene = P.build("parked", seed)
    trace, ego = _traces["by_scene"][id(scene.scenario)]
    s = scene.scenario
    reached.append(ego_log_reaches_goal(s))
    yields.append(sum(1 for step in trace if step["stop"][ego].any()))
    valid = s.log_valid[ego]
    slow.append(bool(s.log_speed[ego][valid].min() < 2.0))
    distance.append(float(np.linalg.norm(s.goal_xy[ego] - s.log_xy[ego][valid][0])))
    separation.append(_traces["separation"][-1])   # the draw that was kept is the last one built
print(f"parked seeds 0-39: ego log reaches its goal in {sum(reached)} / 40; the ego yields in "
      f"{sum(y > 0 for y in yields)} / 40 (median {np.median(yields) / 10:.1f} s); slows below 2 m/s in "
      f"{sum(slow)} / 40; start to goal {np.mean(distance):.0f} m (straight line, mean); bypass middle to "
      f"oncoming lane {min(separation):.2f}-{max(separation):.2f} m (median {np.median(separation):.2f})")

P.drive, P._drive_clean, P._build_once = _drive, _clean, _once
P._BUILDERS["parked"] = _parked
per_family: dict[str, list[bool]] = {}
for s in train_pool(120, seed=0):
    for a in np.nonzero(s.controllable)[0]:
        last = np.nonzero(s.log_valid[a])[0][-1]
        per_family.setdefault(s.family, []).append(bool(np.linalg.norm(s.log_xy[a, last] - s.goal_xy[a]) <= 2.0))
every = [x for v in per_family.values() for x in v]
print(f"train_pool(120): controllable agents whose log reaches the goal {100 * np.mean(every):.1f} %; "
      + ", ".join(f"{f} {100 * np.mean(v):.0f} %" for f, v in per_family.items()))
pool = eval_pool(400, seed=0)
dropped = Counter(s.family for s in pool if not ego_log_reaches_goal(s))
print(f"eval_pool(400, seed=0): {sum(dropped.values())} of {len(pool)} scenes dropped ({dict(dropped)})")
