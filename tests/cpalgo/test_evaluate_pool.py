"""``make_tasks`` / ``Evaluator`` on a folder of WOMD files (``--pool FOLDER``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cpsim.simulator")

from cpalgo.evaluate import runner as R  # noqa: E402
from cpsim.scenario import interactive_split, random_split  # noqa: E402
from tests.cpsim.test_splits import womd_folder  # noqa: E402


def _keys(items) -> list[tuple[str, int]]:
    return [(t.scenario_id, t.ego) if isinstance(t, R.Task) else (t.id, t.ego_index) for t in items]


def test_make_tasks_on_a_womd_folder_uses_the_folder_splits(tmp_path: Path) -> None:
    folder = womd_folder(tmp_path / "womd")  # 12 track tasks in 4 .json.gz scenes, 7 eligible
    tasks = R.make_tasks(folder, "both", 5, seed=2)
    inter = [t for t in tasks if t.split == "interactive"]
    rand = [t for t in tasks if t.split == "random"]
    assert _keys(inter) == _keys(interactive_split(folder, 5))
    assert _keys(rand) == _keys(random_split(folder, 5, seed=2))
    assert [t.index for t in rand] == list(range(5))
    # n is clamped to the eligible tasks in both splits
    assert len(R.make_tasks(str(folder), "random", 50)) == len(R.make_tasks(folder, "interactive", 50)) == 7


def test_make_tasks_rejects_a_pool_smaller_than_n_and_a_negative_seed() -> None:
    with pytest.raises(ValueError, match="pool_size: expected a whole number >= n"):
        R.make_tasks("procedural", "random", 3, pool_size=1)
    with pytest.raises(ValueError, match="seed: expected a whole number >= 0"):
        R.make_tasks("procedural", "random", 3, seed=-1)
    from cpalgo.evaluate import Evaluator  # the README's import

    assert Evaluator is R.Evaluator


def test_evaluator_simulates_each_ego_of_a_scene(tmp_path: Path) -> None:
    folder = womd_folder(tmp_path / "womd")
    tasks = R.make_tasks(folder, "interactive", 7)
    assert len({t.scenario_id for t in tasks}) < len(tasks)  # some scenes give several tasks
    ev = R.Evaluator(tasks, ["replay"], config=R.EvalConfig(progress=False, max_worlds=8, record=tuple(range(7))))
    assert len(ev.scenarios) == 7  # one simulator scenario per (scene, ego)
    res = ev.run("expert")
    assert _keys(tasks) == list(zip(res.columns["scenario_id"].tolist(), res.columns["ego"].tolist()))
    for row, task in enumerate(tasks):  # slot 0 starts where that task's ego starts in its log
        np.testing.assert_allclose(res.trajectories[row]["xy"][0, 0], task.scenario.log_xy[task.ego, 0], atol=1e-3)
        np.testing.assert_allclose(res.trajectories[row]["goal_xy"], task.scenario.goal_xy[task.ego], atol=1e-3)


def test_procedural_tasks_are_scenes_whose_log_reaches_its_goal() -> None:
    # BehaviorBench's goal is the log's final position; a procedural scene whose logged ego
    # stops short of its goal (a few T-junction and intersection scenes) is no task
    from cpsim.scenario import ego_log_reaches_goal, eval_pool

    pool = eval_pool(12, seed=4)  # two scenes per family: the pool make_tasks draws below
    short = {sc.id for sc in pool if not ego_log_reaches_goal(sc)}
    assert short, "the pool should hold a scene whose log falls short, or this test checks nothing"
    tasks = R.make_tasks("procedural", "random", 12, seed=4, pool_size=12)  # Random-12 of 12 takes all it may
    assert {t.scenario_id for t in tasks} == {sc.id for sc in pool} - short
    assert all(ego_log_reaches_goal(t.scenario) for t in tasks)
