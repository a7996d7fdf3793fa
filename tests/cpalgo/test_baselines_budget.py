"""The six adapted baselines under the equal-budget contract: ``learn(B)`` stops at the
rollout step where B_post (main + continuation transitions) reaches B, and a
tiny ``counterplay experiment`` grid runs all six end to end."""

from __future__ import annotations

import csv
import io

import pytest

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from cpalgo.experiments.runner import run_experiment  # noqa: E402
from cpalgo.methods import build_method, get_method, method_names  # noqa: E402
from cpalgo.recipes import CosineSchedule  # noqa: E402
from tests.cpalgo.test_baselines_common import (  # noqa: E402,F401
    ALGO,
    ALL_METHODS,
    CONTINUATION_METHODS,
    anchor,
    make_env,
    save_anchor,
    tiny_settings,
)

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py

RECIPE = """cpsim/SelfPlay-v0:
  policy: 'MlpLstmPolicy'
  n_envs: 8
  n_timesteps: 600
  n_steps: 40
  batch_size: 64
  n_epochs: 1
  learning_rate: cosine(3e-4)
  policy_kwargs: "dict(lstm_hidden_size=16, enable_critic_lstm=False, net_arch=[32])"
  env_kwargs:
    max_agents: 4
    num_scenarios: 4
    episode_steps: 40
"""


def test_counterplay_methods_lists_the_six_as_baselines(capsys):
    from cpalgo.cli import main

    assert main(["methods"]) == 0
    listed = {line.split()[0]: line.split()[1] for line in capsys.readouterr().out.splitlines() if line.strip()}
    assert all(listed.get(name) == "baseline" for name in ALL_METHODS)
    names = method_names()
    for name in ALL_METHODS:
        assert name in names
        spec = get_method(name)
        assert spec.group == "baseline" and spec.row_label.endswith("\u2020")
    # table order: the PPO baselines, then the six, then CounterPlay
    assert names.index("ppo-opponent") < names.index("spiced") < names.index("craft") < names.index("counterplay")


@pytest.mark.parametrize("name", ALL_METHODS)
def test_every_baseline_stops_at_the_same_budget(anchor, name):
    budget = 900
    model = build_method(name, anchor, make_env(), algo_kwargs=dict(ALGO, learning_rate=CosineSchedule(3e-4)),
                         settings=tiny_settings(name), seed=0)
    model.learn(budget)
    b = model.budget
    # stopped at the rollout step that reached it: within one step of the live slots
    assert budget <= b.total < budget + model.n_envs
    before_last = sum(g["main"] + g["branch"] for g in b.history[:-1])
    assert before_last < budget
    assert model.num_timesteps == b.total  # SB3's counter is B_post too
    assert model._current_progress_remaining == pytest.approx(max(0.0, 1.0 - b.total / budget))
    assert model.policy.optimizer.param_groups[0]["lr"] < 0.5 * 3e-4  # annealed over the budget
    if name in CONTINUATION_METHODS:
        # continuations are part of B_post, within each generation's allowance
        assert b.candidate > 0 and b.candidate == model.continuation_totals["continuation_transitions"]
        for g in b.history:
            assert g["branch"] <= model.branch_cap * g["cap_main"]
    else:
        assert b.branch == 0


def test_a_tiny_experiment_grid_runs_all_six_end_to_end(tmp_path):
    recipe = tmp_path / "recipe.yml"
    recipe.write_text(RECIPE)
    anchor_path = save_anchor(tmp_path / "anchor.zip")
    doc = {"name": "baselines", "anchor": anchor_path, "recipe": str(recipe), "budget": 500, "seeds": [0],
           "methods": ["ppo-continue", *ALL_METHODS], "checkpoint_every": 1,
           "method_settings": {name: tiny_settings(name) for name in ALL_METHODS if tiny_settings(name)},
           "evaluation": {"tasks": 1, "regimes": ["idm"], "deployments": ["normal"], "max_worlds": 8}}
    result = run_experiment(doc, tmp_path / "out", backend="sequential", progress=False)
    assert result.ok, result.runs
    assert all(status == "done" for status in result.runs.values())
    rows = list(csv.DictReader(io.StringIO((tmp_path / "out" / "results.csv").read_text())))
    methods = {r[next(iter(r))] for r in rows}
    assert {"anchor", "ppo-continue", *ALL_METHODS} <= methods
    tables = (tmp_path / "out" / "tables.md").read_text()
    for label in ("SPICED", "CL4AD", "DAPO", "VinePPO", "PlannerRFT", "CRAFT"):
        assert label in tables
