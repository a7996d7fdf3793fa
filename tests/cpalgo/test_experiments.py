"""Experiment grids (cpalgo.experiments): grid errors, resume, tables, the Ray path and the
main job, on tiny settings (2 worlds x 4 slots, LSTM 16, one or two evaluation tasks)."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from cpalgo.evaluate.metrics import OutcomeClass  # noqa: E402
from cpalgo.experiments.grid import ANCHOR, GridError, RunSpec, load_grid  # noqa: E402
from cpalgo.experiments.runner import ray_available, run_experiment, runs_of  # noqa: E402
from cpalgo.experiments.runs import run_dir  # noqa: E402
from cpalgo.experiments.tables import collect_results, markdown_report, paired_difference, repaired, results_csv  # noqa: E402
from cpalgo.methods.base import BudgetedCounterPlay  # noqa: E402
from cpsim import SelfPlayVecEnv  # noqa: E402
from cpsim.atomic import write_bytes_atomic  # noqa: E402

EPISODE = 40
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


pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, str]:
    """A tiny anchor (default observation layout, so the evaluator fits it) and its recipe."""
    folder = tmp_path_factory.mktemp("grid")
    recipe = folder / "recipe.yml"
    recipe.write_text(RECIPE)
    env = SelfPlayVecEnv(num_worlds=2, max_agents=4, num_scenarios=4, seed=0, episode_steps=EPISODE)
    anchor = folder / "anchor.zip"
    BudgetedCounterPlay("MlpLstmPolicy", env, counterfactual=False, seed=0, n_steps=EPISODE, batch_size=64,
                        n_epochs=1, policy_kwargs=dict(lstm_hidden_size=16, enable_critic_lstm=False,
                                                       net_arch=[32])).save(anchor)
    return {"anchor": str(anchor), "recipe": str(recipe), "folder": str(folder)}


def grid_doc(files, **changes):
    doc = {"name": "tiny", "anchor": files["anchor"], "recipe": files["recipe"], "budget": 500, "seeds": [0],
           "methods": ["ppo-continue"], "checkpoint_every": 1,
           "evaluation": {"tasks": 1, "regimes": ["idm"], "deployments": ["normal"], "max_worlds": 8}}
    doc.update(changes)
    return doc


# ----------------------------------------------------------------------------- grid errors
@pytest.mark.parametrize("change, message", [
    ({"methods": ["ppo-continue", "ppo-nonsense"]}, "methods: unknown method 'ppo-nonsense'"),
    ({"budget": 0}, "budget: must be > 0"),
    ({"budget": -5}, "budget: must be > 0"),
    ({"anchor": "missing/anchor.zip"}, "anchor: no such checkpoint"),
    ({"evaluation": {"deployments": ["normal", "reckless"]}}, "evaluation.deployments: unknown deployment 'reckless'"),
    ({"seedz": [0]}, "seedz: unknown key"),
    ({"evaluation": {"taskz": 3}}, "evaluation.taskz: unknown key"),
    ({"evaluation": {"regimes": ["idm", "tanks"]}}, "evaluation.regimes: unknown regime 'tanks'"),
    ({"method_settings": {"ppo-continue": {"rewind_depth": 3}}}, "method_settings.ppo-continue.rewind_depth"),
    ({"method_settings": {"ppo-rewind": {"rewind_depth": 3}}}, "method_settings.ppo-rewind: is not one of"),
    ({"overrides": {"learning_rate": "sometimes(3)"}}, "overrides.learning_rate"),
    ({"env": {"num_wheels": 3}}, "env.num_wheels"),
    ({"seeds": [0, 0]}, "seeds: lists a seed twice"),
    ({"order": "random"}, "order: expected one of ['seeds', 'methods'], got 'random'"),
    ({"evaluation": {"coplayers": "everyone"}}, "evaluation.coplayers: expected 'vehicles' or 'controllable'"),
    ({"evaluation": {"seed": [0, 1, 0]}}, "evaluation.seed: lists a task set twice"),
    ({"evaluation": {"seed": []}}, "evaluation.seed: expected a whole number or a non-empty list"),
    ({"evaluation": {"seed": [0, -1]}}, "evaluation.seed: must be >= 0, got -1"),
    ({"evaluation": {"seed": [0, 1.5]}}, "evaluation.seed: expected a whole number, got 1.5"),
    ({"evaluation": {"seed": {"a": 1}}}, "evaluation.seed: expected a whole number or a non-empty list"),
    # values, not only names, are checked before any run (the algorithm's and the env's own checks)
    ({"env": {"num_scenarios": -3}}, "env.num_scenarios: must be a whole number >= 1"),
    ({"env": {"panel_share": 1.5}}, "env.panel_share: expected a number in [0, 1]"),
    ({"overrides": {"batch_size": 0}}, "overrides.batch_size: must be a whole number >= 1"),
    ({"overrides": {"rho": 3}}, "overrides.rho: must lie in [0, 1]"),
    ({"methods": ["counterplay"], "method_settings": {"counterplay": {"window": [60, 5]}}},
     "method_settings.counterplay.window"),
])
def test_bad_grids_fail_before_anything_runs_naming_the_key(files, tmp_path, change, message):
    doc = grid_doc(files)
    for key, value in change.items():
        if key == "evaluation":
            doc["evaluation"] = {**doc["evaluation"], **value}
        else:
            doc[key] = value
    path = tmp_path / "grid.yml"
    path.write_text(yaml.safe_dump(doc))
    out = tmp_path / "out"
    with pytest.raises(GridError) as info:
        run_experiment(str(path), out, backend="sequential", progress=False)
    text = str(info.value)
    assert message in text and text.startswith(str(path)) and "\n" not in text
    assert not out.exists()  # nothing ran, nothing was written


@pytest.mark.parametrize("change, message", [
    ({"evaluation": {"sim_config": {"episode_steps": -5}}}, "evaluation.sim_config.episode_steps"),
    ({"evaluation": {"tasks": 3, "pool_size": 1}}, "evaluation.pool_size: must be >= 3"),
])
def test_bad_grid_values_fail_before_anything_runs(files, tmp_path, change, message):
    doc = grid_doc(files)
    doc["evaluation"] = {**doc["evaluation"], **change["evaluation"]}
    with pytest.raises(GridError, match=message):
        load_grid(doc)
    junk = tmp_path / "anchor.zip"
    junk.write_text("not a checkpoint")
    with pytest.raises(GridError, match="anchor: .* is not an SB3 checkpoint"):
        load_grid(grid_doc(files, anchor=str(junk)))


def test_damaged_run_folders_are_redone_or_refused(files, tmp_path):
    """Without training: an unreadable evaluation is redone, a corrupt checkpoint is moved
    aside (the run starts over), runs without their grid record or from another anchor's
    weights are refused."""
    import shutil

    from cpalgo.experiments.runner import _check_out
    from cpalgo.experiments.runs import _readable_checkpoint, load_columns, run_status

    anchor = tmp_path / "anchor.zip"
    shutil.copy(files["anchor"], anchor)
    grid = load_grid(grid_doc(files, anchor=str(anchor)))
    out = tmp_path / "out"
    spec = RunSpec("ppo-continue", 0)
    folder = run_dir(out, spec)
    folder.mkdir(parents=True)
    (folder / "train.json").write_text("{}")
    (folder / "model.zip").write_bytes(b"weights")
    write_bytes_atomic(folder / "eval_normal.npz", b"PK\x03\x04 truncated")
    assert run_status(grid, out, spec) == "evaluate"  # a truncated evaluation is not trusted
    with pytest.raises(ValueError, match="eval_normal.npz: unreadable evaluation file"):
        load_columns(folder / "eval_normal.npz")
    buf = io.BytesIO()
    np.savez_compressed(buf, score=np.zeros(2))
    write_bytes_atomic(folder / "eval_normal.npz", buf.getvalue())
    assert run_status(grid, out, spec) == "done"
    (folder / "model.zip").unlink()  # a clone with the records only: nothing to redo
    assert run_status(grid, out, spec) == "done"
    (folder / "eval_normal.npz").unlink()  # ... but an evaluation needs the weights
    assert run_status(grid, out, spec) == "new"

    (folder / "checkpoint.zip").write_bytes(b"PK truncated")
    (folder / "checkpoint.json").write_text('{"total": 100}')
    lines: list[str] = []
    assert _readable_checkpoint(folder, spec, lines.append) is None
    assert (folder / "checkpoint.corrupt.zip").is_file() and not (folder / "checkpoint.zip").exists()
    assert "moved aside, starting over" in lines[0]

    with pytest.raises(GridError, match="holds runs but no grid.json"):
        _check_out(grid, out)
    write_bytes_atomic(out / "grid.json", json.dumps({"fingerprint": grid.run_fingerprint()}).encode())
    _check_out(grid, out)  # the same grid resumes
    other = BudgetedCounterPlay.load(files["anchor"])  # the same network, other weights, same path
    with torch.no_grad():
        next(other.policy.parameters()).add_(1.0)
    other.save(anchor)
    with pytest.raises(GridError, match="anchor_weights_sha1 differs"):
        _check_out(load_grid(grid_doc(files, anchor=str(anchor))), out)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(GridError, match="is a file"):
        _check_out(grid, blocker / "out")


def test_experiment_command_prints_one_error_line_and_exits_2(files, tmp_path):
    path = tmp_path / "grid.yml"
    path.write_text(yaml.safe_dump(grid_doc(files, methods=["counterplay", "cp-fixed-99"])))
    proc = subprocess.run([sys.executable, "-m", "cpalgo.cli", "experiment", "--config", str(path), "--out",
                           str(tmp_path / "out"), "--backend", "sequential"], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 2
    errors = [line for line in proc.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and "methods: unknown method 'cp-fixed-99'" in errors[0]
    listing = subprocess.run([sys.executable, "-m", "cpalgo.cli", "methods"], capture_output=True, text=True,
                             timeout=300)
    assert listing.returncode == 0 and "ppo-rewind" in listing.stdout and "distill-cautious" in listing.stdout


def test_shipped_paper_grid_is_valid_and_holds_every_method():
    from cpalgo.methods import method_names

    grid = load_grid("zoo/experiments/paper_small.yml")
    assert set(grid.methods) == set(method_names())
    assert grid.seeds == (0, 1, 2)
    assert set(grid.evaluation.deployments) == {"normal", "halfway", "aggressive"}
    assert set(grid.evaluation.deployments["aggressive"]) == {"anchor", "ppo-continue", "distill-aggressive",
                                                               "distill-cautious", "counterplay"}


def test_selfplay_paper_grids_hold_every_method_on_the_selfplay_recipe():
    """zoo/experiments/paper_selfplay*.yml: every method x 3 seeds from the shipped self-play
    anchor at 1 % and 5 % of its training transitions (zoo/anchor.json), 100 tasks per split,
    all regimes, paper_small's deployments, with zoo/counterplay_selfplay.yml."""
    import json

    from cpalgo.methods import method_names
    from cpalgo.recipes import shipped_path

    transitions = json.loads(shipped_path("anchor.json").read_text())["num_timesteps"]
    small = load_grid("zoo/experiments/paper_small.yml")
    for name, share in (("paper_selfplay", 0.01), ("paper_selfplay_5pct", 0.05)):
        grid = load_grid(f"zoo/experiments/{name}.yml")
        assert Path(grid.anchor).resolve() == shipped_path("anchor.zip").resolve()
        assert abs(grid.budget - share * transitions) <= 0.01 * share * transitions, (name, grid.budget)
        assert grid.seeds == (0, 1, 2) and set(grid.methods) == set(method_names())
        assert grid.recipe.endswith("counterplay_selfplay.yml")
        assert grid.evaluation.tasks == 100 and len(grid.evaluation.regimes) == 8
        assert grid.evaluation.task_sets == (0, 1)  # 100 tasks per split on 2 task sets
        assert ({d: set(who) for d, who in grid.evaluation.deployments.items()}
                == {d: set(who) for d, who in small.evaluation.deployments.items()})


def test_womd_grid_trains_and_evaluates_on_the_womd_folders(monkeypatch):
    """zoo/experiments/womd_selfplay.yml: the self-play recipe and budget of paper_selfplay.yml,
    post-training on the WOMD training scenes and evaluation on the validation scenes (paths
    relative to the project root, as the README names the data folder)."""
    root = Path(__file__).resolve().parents[2]
    if not (root.parent / "shared" / "data" / "womd" / "train").is_dir():
        pytest.skip("WOMD scenes not present (../shared/data/womd)")
    monkeypatch.chdir(root)
    grid = load_grid("zoo/experiments/womd_selfplay.yml")
    paper = load_grid("zoo/experiments/paper_selfplay.yml")
    assert grid.budget == paper.budget and grid.recipe == paper.recipe and grid.anchor == paper.anchor
    assert {"ppo-continue", "counterplay"} <= set(grid.methods) and grid.seeds == (0, 1, 2)
    assert Path(grid.env["womd_dir"]).resolve() == (root.parent / "shared/data/womd/train").resolve()
    assert Path(grid.evaluation.pool).resolve() == (root.parent / "shared/data/womd/valid").resolve()
    # the style ceiling needs the anchor under more than one condition
    assert {"halfway", "aggressive"} <= set(grid.evaluation.deployments)


def test_grid_ppo_policy_drives_the_selfplay_regime(files, tmp_path):
    """``evaluation.ppo_policy``: the selfplay regime's co-player (a classic one for a classic
    anchor, the shipped one being jerk); it reaches the fingerprint only when set, so the
    folders of grids without it still resume."""
    from cpalgo.experiments.runs import _evaluator

    ev = {**grid_doc(files)["evaluation"], "regimes": ["selfplay"], "ppo_policy": files["anchor"]}
    grid = load_grid(grid_doc(files, evaluation=ev))
    assert grid.evaluation.ppo_policy == files["anchor"]
    assert grid.run_fingerprint()["evaluation"]["ppo_policy"] == files["anchor"]
    assert "ppo_policy" not in load_grid(grid_doc(files)).run_fingerprint()["evaluation"]
    evaluator = _evaluator(grid, "normal")
    assert evaluator.ppo_policy.policy.lstm_actor.hidden_size == 16  # the tiny anchor, not zoo/ppo_traffic.zip
    with pytest.raises(GridError, match="evaluation.ppo_policy: no such checkpoint"):
        load_grid(grid_doc(files, evaluation={**ev, "ppo_policy": str(tmp_path / "missing.zip")}))


def test_coplayer_rule_defaults_to_vehicles_and_reaches_the_fingerprint(files):
    """``evaluation.coplayers``: BehaviorBench's ``vehicles`` by default; ``controllable`` (the
    only rule before the setting existed) leaves the fingerprint as it was, so older folders
    still resume, while switching rules changes it."""
    default = load_grid(grid_doc(files))
    assert default.evaluation.coplayers == "vehicles"
    legacy = load_grid(grid_doc(files, evaluation={**grid_doc(files)["evaluation"], "coplayers": "controllable"}))
    assert legacy.evaluation.coplayers == "controllable"
    assert "coplayers" not in legacy.run_fingerprint()["evaluation"]
    assert default.run_fingerprint()["evaluation"]["coplayers"] == "vehicles"
    assert load_grid("zoo/experiments/paper_small.yml").evaluation.coplayers == "vehicles"
    assert load_grid("docs/results/paper_core.yml").evaluation.coplayers == "controllable"  # a record


def test_task_sets_parse_and_keep_the_fingerprint_of_the_first(files):
    """``evaluation.seed``: an int as before, a list of task sets, a list of one = that set;
    the fingerprint holds the first set only (so a folder may grow its list); a folder pool
    cannot give several sets (its interactive split ignores the seed)."""
    def grid(seed, **ev):
        return load_grid(grid_doc(files, evaluation={**grid_doc(files)["evaluation"], "seed": seed, **ev}))

    single, both, one = grid(0), grid([0, 1]), grid([3])
    assert single.evaluation.seed == 0 and single.evaluation.task_sets == (0,)
    assert both.evaluation.seed == (0, 1) and both.evaluation.task_sets == (0, 1)
    assert one.evaluation.seed == 3 and one.evaluation.task_sets == (3,)
    assert both.run_fingerprint() == single.run_fingerprint() != grid([1, 0]).run_fingerprint()
    assert both.as_dict()["evaluation"]["seed"] == [0, 1]
    with pytest.raises(GridError, match="evaluation.seed: several task sets need pool: procedural"):
        grid([0, 1], pool=files["folder"])
    assert grid([0, 1], pool=files["folder"], splits=["random"]).evaluation.task_sets == (0, 1)


def test_run_order_queues_seeds_or_methods_first_and_leaves_the_fingerprint(files):
    def keys(**change):
        return [(r.method, r.seed) for r in load_grid(grid_doc(files, methods=["ppo-continue", "counterplay"],
                                                               seeds=[0, 1], **change)).runs()]

    assert keys() == [("anchor", None), ("ppo-continue", 0), ("counterplay", 0), ("ppo-continue", 1), ("counterplay", 1)]
    assert keys(order="methods") == [("anchor", None), ("ppo-continue", 0), ("ppo-continue", 1),
                                     ("counterplay", 0), ("counterplay", 1)]
    by_methods = load_grid(grid_doc(files, order="methods"))
    assert by_methods.run_fingerprint() == load_grid(grid_doc(files)).run_fingerprint()  # same folder resumes
    assert by_methods.as_dict()["order"] == "methods"


# ----------------------------------------------------------------------------- resume
def test_grid_resumes_skips_finished_runs_and_continues_killed_ones(files, tmp_path):
    out = tmp_path / "out"
    doc = grid_doc(files, methods=["counterplay"])
    first = run_experiment(doc, out, backend="sequential", progress=False)
    assert first.ok and set(first.runs.values()) == {"done"}
    assert all(s == "done" for s in runs_of(load_grid(doc), out).values())
    from cpalgo.experiments.runs import read_checkpoint

    spec = RunSpec("counterplay", 0)
    folder = run_dir(out, spec)
    train = json.loads((folder / "train.json").read_text())
    assert train["b_post"] >= 500 and train["generations"] >= 2
    checkpoint = json.loads((folder / "checkpoint.json").read_text())
    assert 0 < checkpoint["budget"]["generations"] < train["generations"]
    assert read_checkpoint(folder) == checkpoint  # the counters inside the zip, which resumes
    # "kill" the counterplay run after its first checkpoint: only the checkpoint survives
    for name in ("train.json", "model.zip", "eval_normal.npz"):
        (folder / name).unlink()
    anchor_eval = run_dir(out, RunSpec("anchor", None)) / "eval_normal.npz"
    stamp = anchor_eval.stat().st_mtime_ns
    assert runs_of(load_grid(doc), out)["counterplay/seed0"] == "resume"
    second = run_experiment(doc, out, backend="sequential", progress=False)
    assert second.runs == {"anchor": "skipped", "counterplay/seed0": "done"}
    assert anchor_eval.stat().st_mtime_ns == stamp  # finished work is not redone
    resumed = json.loads((folder / "train.json").read_text())
    b = checkpoint["budget"]
    assert resumed["resumed_from"] == b["main"] + b["factual"] + b["candidate"] + b["verification"]
    assert resumed["b_post"] >= 500
    assert resumed["generations"] > checkpoint["budget"]["generations"]
    # the tables cover every run
    rows = (out / "results.csv").read_text().splitlines()
    assert {r.split(",")[0] for r in rows[1:]} == {"anchor", "counterplay"}
    tables = (out / "tables.md").read_text()
    assert "Table I" in tables
    # a different grid in the same folder is refused, naming what differs
    with pytest.raises(GridError, match="budget differs"):
        run_experiment({**doc, "budget": 900}, out, backend="sequential", progress=False)


def test_task_sets_are_evaluated_apart_and_added_without_training_again(files, tmp_path):
    """A grid of one task set grown to two evaluates the trained run and the anchor on the
    new set only (no training, the first set's files untouched); results.csv gets a row per
    set, the tables pool them; a rerun skips everything; the first set must stay first."""
    import csv

    out = tmp_path / "out"
    doc = grid_doc(files, budget=200)
    first = run_experiment(doc, out, backend="sequential", progress=False)
    assert first.ok, first.errors
    assert (out / "results.csv").read_text().startswith("method,seed,split,regime,deployment,n_tasks,")
    folder, anchor = run_dir(out, RunSpec("ppo-continue", 0)), run_dir(out, RunSpec("anchor", None))
    kept = [folder / "model.zip", folder / "train.json", folder / "eval_normal.npz", anchor / "eval_normal.npz"]
    stamps = [p.stat().st_mtime_ns for p in kept]

    grown = {**doc, "evaluation": {**doc["evaluation"], "seed": [0, 1]}}
    assert runs_of(load_grid(grown), out) == {"anchor": "evaluate", "ppo-continue/seed0": "evaluate"}
    second = run_experiment(grown, out, backend="sequential", progress=False)
    assert second.ok and second.runs == {"anchor": "done", "ppo-continue/seed0": "done"}, second.errors
    assert [p.stat().st_mtime_ns for p in kept] == stamps  # not trained, set 0 not evaluated again
    assert (folder / "eval_normal.taskset1.npz").is_file() and (anchor / "eval_normal.taskset1.npz").is_file()

    with open(out / "results.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0])[:7] == ["method", "seed", "split", "regime", "deployment", "task_set", "n_tasks"]
    assert {(r["method"], r["split"], r["task_set"]) for r in rows} == {
        (m, split, t) for m in ("anchor", "ppo-continue") for split in ("interactive", "random") for t in "01"}
    res = collect_results(out, load_grid(grown))
    for method, seed in (("anchor", None), ("ppo-continue", 0)):
        for split in ("interactive", "random"):
            per_set = [float(r["score"]) for r in rows if (r["method"], r["split"]) == (method, split)]
            assert res.values(method, "normal", split, "idm", "score") == pytest.approx([np.mean(per_set)], abs=1e-3)
            assert res.summary[(method, seed, "normal", split, "idm")]["n"] == 2  # one task per split and set
    tables = (out / "tables.md").read_text()
    assert "2 task sets: seeds 0, 1" in tables and "(2 tasks over task sets 0, 1, pooled)" in tables

    third = run_experiment(grown, out, backend="sequential", progress=False)
    assert set(third.runs.values()) == {"skipped"}
    with pytest.raises(GridError, match="evaluated first on task set 0 .evaluation.seed differs"):
        run_experiment({**doc, "evaluation": {**doc["evaluation"], "seed": [1, 0]}}, out, backend="sequential",
                       progress=False)


# ----------------------------------------------------------------------------- tables
def _columns(split_regimes, goal, af, naf, off, score):
    n = len(goal)
    cols = {
        "split": np.array([s for s, _ in split_regimes]), "regime": np.array([r for _, r in split_regimes]),
        "task": np.arange(n) % 2, "scenario_id": np.array([f"s{i % 2}" for i in range(n)]),
        "ego": np.zeros(n, np.int64), "goal": np.array(goal, bool), "at_fault_collision": np.array(af, bool),
        "non_at_fault_collision": np.array(naf, bool), "offroad": np.array(off, bool),
        "score": np.array(score, float), "co_player_harm": np.zeros(n, np.int64),
    }
    cols["timeout"] = ~(cols["goal"] | cols["at_fault_collision"] | cols["non_at_fault_collision"] | cols["offroad"])
    cols["outcome_class"] = np.select(
        [cols["at_fault_collision"], cols["offroad"], cols["goal"], cols["non_at_fault_collision"]],
        [int(OutcomeClass.AT_FAULT_COLLISION), int(OutcomeClass.OFFROAD), int(OutcomeClass.COMPLETED),
         int(OutcomeClass.NON_AT_FAULT_COLLISION)], default=int(OutcomeClass.TIMEOUT)).astype(np.int8)
    return cols


def _put_eval(out, method, seed, dep, cols):
    """Write ``cols`` as the run's ``eval_<dep>.npz``, as the runner would."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **cols)
    write_bytes_atomic(run_dir(out, RunSpec(method, seed)) / f"eval_{dep}.npz", buf.getvalue())


def test_tables_report_scores_repairs_and_targets_from_the_runs_files(files, tmp_path):

    doc = grid_doc(files, methods=["ppo-continue", "counterplay", "cp-no-style", "distill-aggressive"], seeds=[0, 1],
                   evaluation={"tasks": 2, "splits": ["interactive"], "regimes": ["idm", "replay"],
                               "deployments": {"normal": "all", "aggressive": ["anchor", "counterplay"]}})
    grid = load_grid(doc)
    out = tmp_path / "out"
    sr = [("interactive", "idm")] * 2 + [("interactive", "replay")] * 2

    def put(method, seed, dep, cols):
        _put_eval(out, method, seed, dep, cols)

    # anchor: task-regimes 0, 1 time out, 2 completes, 3 collides at fault
    anchor = _columns(sr, [0, 0, 1, 0], [0, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 60, 0])
    put("anchor", None, "normal", anchor)
    put("anchor", None, "aggressive", anchor)
    # counterplay repairs both timeouts (seed 0) or one (seed 1), keeps the completion
    put("counterplay", 0, "normal", _columns(sr, [1, 1, 1, 0], [0, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0], [80, 80, 80, 0]))
    put("counterplay", 1, "normal", _columns(sr, [1, 0, 1, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1], [70, 0, 70, 0]))
    put("counterplay", 0, "aggressive", _columns(sr, [1, 1, 1, 1], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [90] * 4))
    # ppo-continue repairs nothing; one of its completions hits someone (not a repair, no score)
    for seed in (0, 1):
        put("ppo-continue", seed, "normal", _columns(sr, [0, 0, 1, 0], [0, 0, 0, 1], [0, 0, 1, 0], [0, 0, 0, 0], [0, 0, 0, 0]))
        put("cp-no-style", seed, "normal", _columns(sr, [0, 1, 1, 0], [0] * 4, [0] * 4, [0] * 4, [0, 10, 10, 0]))
        # the aggressive distillation control: one at-fault collision more than CounterPlay's seed 0
        put("distill-aggressive", seed, "normal", _columns(sr, [1, 1, 0, 0], [0, 0, 1, 1], [0] * 4, [0] * 4, [50, 50, 0, 0]))
    # search counters of the two counterplay seeds: 2 searches x 5 retries each
    for seed, (incomplete, not_better, harms, admitted) in ((0, (6, 2, 1, 1)), (1, (8, 0, 0, 2))):
        totals = {"failures": 4, "searches": 2, "teachers_chosen": 1, "admissible": admitted, "verified": 1,
                  "teachers": 1, "factual_completed": seed, "retries_incomplete": incomplete,
                  "retries_not_better": not_better, "retries_harms_other": harms, "retries_admitted": admitted,
                  # roots 5 and 60 (seed 0) or 30 and 60 (seed 1) decisions back; one teacher each
                  "failures_timeout": 2 + seed, "root_depth_sum": 65 if seed == 0 else 90,
                  "root_depth_5" if seed == 0 else "root_depth_30": 1, "root_depth_60": 1,
                  "profile_aggressive" if seed == 0 else "profile_cautious": 1}
        for method in ("counterplay", "cp-no-style"):
            write_bytes_atomic(run_dir(out, RunSpec(method, seed)) / "train.json", json.dumps(
                {"generations": 2, "b_post": 1000, "wall_s": 60.0, "budget_totals": {"branch_share": 0.25},
                 "totals": {"search_totals": totals}}).encode())
    res = collect_results(out, grid)
    assert res.values("counterplay", "normal", "interactive", "mean", "score") == [80.0 * 3 / 4, 70.0 * 2 / 4]
    assert not repaired(res.evals[("ppo-continue", 0, "normal")])[2]  # a non-at-fault collision is no repair
    md = markdown_report(res)
    # Table I: per regime (idm: seeds 80 and 35 -> 57.5 ± 31.8; replay: 40 and 35) and the difference row
    assert "| Anchor | 0.0 | 30.0 | 15.0 |" in md
    assert "| CounterPlay | 57.5 ± 31.8 | 37.5 ± 3.5 | 47.5 ± 17.7 |" in md
    assert "| CounterPlay − PPO-Continue | +57.5 | +37.5 | +47.5 |" in md
    # Table III: anchor shares; CounterPlay repairs 100% / 50% of the timeouts, PPO-Continue 0%
    assert "| Anchor (share) | 25.0 (1) | 50.0 (2) | 25.0 (1) | 0.0 (0) | 0.0 (0) |" in md
    assert "| CounterPlay | 100.0 ± 0.0 | 75.0 ± 35.4 | 0.0 ± 0.0 | - | - |" in md
    assert "| PPO-Continue | 0.0 ± 0.0 | 0.0 ± 0.0 | 0.0 ± 0.0 | - | - |" in md
    # Table II lists the ablation; Table IV the aggressive deployment (counterplay: one seed there)
    assert "| No change in driving style | value | - | yes | yes | 5.00 ± 0.00 |" in md
    assert "| CounterPlay | 47.50 ± 17.68 | 12.50 ± 17.68 | 90.00 | 0.00 |" in md
    # which filter the retries failed: (60, 80) % incomplete, (20, 0) not better, (10, 0) harms, (10, 20) admitted
    assert "| CounterPlay | 70.0 ± 14.1 | 10.0 ± 14.1 | 5.0 ± 7.1 | 15.0 ± 7.1 | 25.0 ± 35.4 |" in md
    # where the roots lie (depths 5, 60 / 30, 60: means 32.5 and 45; nearest 50 / 0 %, far edge 50 %)
    # and which styles win (aggressive / cautious, one teacher per seed); without a style change
    # the teachers drive the agent's own condition whatever panel slot found them
    assert ("| CounterPlay | 62.5 ± 17.7 | 38.8 ± 8.8 | 25.0 ± 35.4 | 50.0 ± 0.0 | 50.0 ± 70.7 | 0.0 ± 0.0 "
            "| 0.0 ± 0.0 | 0.0 ± 0.0 | 50.0 ± 70.7 | - |") in md
    assert "| No change in driving style | 62.5 ± 17.7 | 38.8 ± 8.8 | 25.0 ± 35.4 | 50.0 ± 0.0 | - | - | - | - | - | 100.0 |" in md
    # targets: measured and judged
    assert "| CounterPlay − PPO-Continue, interactive: >= +5 points | +47.50" in md
    assert "timeouts repaired, interactive: CounterPlay >= 30%, PPO-Continue <= 10% | 75.0% vs 0.0% | yes |" in md
    assert "full method highest, cp-no-style lowest of the variants | highest counterplay (47.50), lowest cp-no-style" in md
    # Table IV's target: CounterPlay 47.5 at (25 + 0) / 2 % at fault, the control 25.0 at 50 %
    assert "at no higher at-fault collision rate | 47.50 at 12.50% vs 25.00 at 50.00% | yes |" in md
    assert "| verified teachers per generation (CounterPlay) >= 10 | 0.50 | **no** |" in md  # 1 teacher in 2 generations
    # paired differences from PPO-Continue (0 everywhere): CounterPlay 47.5, the anchor 15 (one
    # seed: only the tasks resampled); the target row carries the same interval
    assert "| CounterPlay | 2 | +47.50 [" in md and "| Anchor | 1 | +15.00 [" in md
    paired_row = next(line for line in md.splitlines() if line.startswith("| CounterPlay | 2 | +47.50 ["))
    lo, hi = (float(x) for x in paired_row.split("[")[1].split("]")[0].split(","))
    assert 0.0 <= lo < 47.5 < hi <= 80.0
    assert f"| CounterPlay − PPO-Continue, interactive: >= +5 points | +47.50 [95 % interval {lo:+.2f}, {hi:+.2f}]" in md
    # the ablations also against CounterPlay (5 - 47.5), below their row against PPO-Continue
    against_cp = md.split("## Paired differences from CounterPlay")[1]
    assert "| No change in driving style | 2 | -42.50 [" in against_cp and "| Anchor |" not in against_cp
    assert "sample standard deviation (n − 1)" in md  # 57.5 ± 31.8 is the n − 1 std of 80 and 35
    csv_rows = results_csv(res).splitlines()
    assert csv_rows[0].startswith("method,seed,split,regime,deployment,n_tasks,score,completion_pct")
    assert "counterplay,1,interactive,replay,normal,2,35.0000,50.0000,0.0000,0.0000,50.0000,0.0000,0.0000" in csv_rows

    # a run evaluated on other tasks than the anchor is named in Table III, not dropped; a run
    # missing a regime gets no regime mean (it would not compare with the others)
    other = _columns(sr, [1, 1, 1, 1], [0] * 4, [0] * 4, [0] * 4, [50] * 4)
    other["ego"] = np.asarray(other["ego"]) + 1
    put("ppo-continue", 0, "normal", other)
    idm_only = {k: np.asarray(v)[:2] for k, v in _columns(sr, [1] * 4, [0] * 4, [0] * 4, [0] * 4, [60] * 4).items()}
    put("cp-no-style", 1, "normal", idm_only)
    res = collect_results(out, grid)
    md = markdown_report(res)
    assert "| PPO-Continue (tasks differ from the anchor's: no repair analysis) | - |" in md
    assert "| CounterPlay | 2 | tasks differ |" in md  # no pairing across different tasks
    assert res.values("cp-no-style", "normal", "interactive", "mean", "score") == [5.0]  # seed 1 has no mean


def test_paired_difference_cancels_task_difficulty_and_resamples_whole_tasks():
    rng = np.random.default_rng(1)
    difficulty = np.repeat(rng.normal(70.0, 15.0, 50), 4)  # 50 tasks x 4 regimes, shared by both methods
    cluster = np.repeat(np.arange(50), 4)
    b = np.repeat(difficulty[None], 3, axis=0)
    # a constant shift on every row: the pairing cancels the tasks, the interval is the point
    d, lo, hi = paired_difference(b + 3.0, b, cluster)
    assert d == pytest.approx(3.0) and lo == pytest.approx(3.0) and hi == pytest.approx(3.0)
    # seed offsets of +-1 around a shift of 2: the interval holds 2, excludes 0 and is about the
    # seeds' spread wide, far narrower than the tasks' spread (15 points) would make it unpaired
    a = b + 2.0 + np.array([[-1.0], [0.0], [1.0]])
    d, lo, hi = paired_difference(a, b, cluster)
    assert d == pytest.approx(2.0) and 0.0 < lo < 2.0 < hi < 4.0
    # a task's regimes are drawn together: repeating each row within its task changes nothing
    d2, lo2, hi2 = paired_difference(np.repeat(a, 2, axis=1), np.repeat(b, 2, axis=1), np.repeat(cluster, 2))
    assert (d2, lo2, hi2) == pytest.approx((d, lo, hi))
    # a per-task gain shared by a task's regimes: drawing rows as independent tasks would make
    # the interval narrower than the data support
    gain = b + np.repeat(rng.normal(2.0, 3.0, 50), 4)[None]
    _, lo3, hi3 = paired_difference(gain, b, cluster)
    _, lo4, hi4 = paired_difference(gain, b, np.arange(200))
    assert hi4 - lo4 < 0.6 * (hi3 - lo3)  # about 1/2: four regimes per task
    with pytest.raises(ValueError, match="share a nonzero number of rows"):
        paired_difference(a, b[:, :10], cluster)
    with pytest.raises(ValueError, match=r"\(seeds, rows\)"):
        paired_difference(a[0], b, cluster)
    with pytest.raises(ValueError, match="level"):
        paired_difference(a, b, cluster, level=1.5)


def test_style_ceiling_counts_the_anchor_failures_another_condition_repairs(files, tmp_path):
    """From written files: of the anchor's three normal-deployment failures, its aggressive
    deployment completes one cleanly and its halfway another, which no method repairs."""
    doc = grid_doc(files, methods=["ppo-continue", "counterplay"], seeds=[0, 1],
                   evaluation={"tasks": 2, "splits": ["interactive"], "regimes": ["idm", "replay"],
                               "deployments": {"normal": "all", "halfway": ["anchor"], "aggressive": ["anchor"]}})
    grid = load_grid(doc)
    out = tmp_path / "out"
    sr = [("interactive", "idm")] * 2 + [("interactive", "replay")] * 2

    def put(method, seed, dep, cols):
        _put_eval(out, method, seed, dep, cols)

    # normal: 0 times out, 1 collides at fault, 2 completes, 3 completes after a non-at-fault collision
    put("anchor", None, "normal", _columns(sr, [0, 0, 1, 1], [0, 1, 0, 0], [0, 0, 0, 1], [0] * 4, [0, 0, 60, 0]))
    # aggressive completes 0 and 3 (3 collides on the way: no repair) and breaks 2
    put("anchor", None, "aggressive", _columns(sr, [1, 0, 0, 1], [0, 1, 0, 0], [0, 0, 1, 1], [0] * 4, [90, 0, 0, 0]))
    # halfway completes 1 cleanly
    put("anchor", None, "halfway", _columns(sr, [0, 1, 1, 1], [0, 0, 0, 0], [0, 0, 0, 1], [0] * 4, [0, 70, 50, 0]))
    for seed, goal in ((0, [1, 0, 1, 0]), (1, [1, 1, 1, 0])):  # counterplay repairs 1 or 2 of the 3
        put("counterplay", seed, "normal", _columns(sr, goal, [0] * 4, [0] * 4, [0] * 4, [50 * g for g in goal]))
        put("ppo-continue", seed, "normal", _columns(sr, [0, 0, 1, 1], [0] * 4, [0] * 4, [0] * 4, [0, 0, 60, 60]))
    md = markdown_report(collect_results(out, grid))
    assert "| Split | anchor failures | halfway % | aggressive % | any condition % | PPO-Continue % | CounterPlay % |" in md
    # 3 failures (0, 1, 3): halfway repairs 1, aggressive 0, either 2; the best score per task
    # is (90, 70, 60, 0) -> 55.0 against the normal deployment's 15.0
    assert "| interactive | 3 of 4 | 33.3 | 33.3 | 66.7 | 33.3 ± 0.0 | 50.0 ± 23.6 | 15.0 | 55.0 |" in md


def test_tables_pool_task_sets_of_the_runs_that_have_every_set(files, tmp_path):
    """From written files, no training: a run's task sets pool into one value per seed (mean
    over the sets), a run missing a set stays out of the tables but keeps its rows in
    results.csv, and Table III compares the pooled task-regimes."""
    doc = grid_doc(files, methods=["ppo-continue"], seeds=[0, 1],
                   evaluation={"tasks": 2, "splits": ["interactive"], "regimes": ["idm"],
                               "deployments": ["normal"], "seed": [4, 2]})
    grid = load_grid(doc)
    out = tmp_path / "out"
    sr = [("interactive", "idm")] * 2

    def put(method, seed, task_set, score):
        buf = io.BytesIO()
        goal = [s > 0 for s in score]
        np.savez_compressed(buf, **_columns(sr, goal, [0, 0], [0, 0], [0, 0], score))
        name = "eval_normal.npz" if task_set == 4 else f"eval_normal.taskset{task_set}.npz"
        write_bytes_atomic(run_dir(out, RunSpec(method, seed)) / name, buf.getvalue())

    put("anchor", None, 4, [0, 40])
    put("anchor", None, 2, [0, 0])
    put("ppo-continue", 0, 4, [60, 40])  # set 4: 50, set 2: 30 -> 40
    put("ppo-continue", 0, 2, [60, 0])
    put("ppo-continue", 1, 4, [80, 80])  # no task set 2 yet: not in the tables
    res = collect_results(out, grid)
    assert res.values("ppo-continue", "normal", "interactive", "mean", "score") == [40.0]
    assert res.values(ANCHOR, "normal", "interactive", "mean", "score") == [10.0]
    assert np.array_equal(res.evals[("ppo-continue", 0, "normal")]["task_set"], [4, 4, 2, 2])
    rows = results_csv(res).splitlines()
    assert rows[0].startswith("method,seed,split,regime,deployment,task_set,n_tasks,score")
    assert [r.split(",")[:7] for r in rows[1:]] == [
        ["anchor", "", "interactive", "idm", "normal", "4", "2"], ["anchor", "", "interactive", "idm", "normal", "2", "2"],
        ["ppo-continue", "0", "interactive", "idm", "normal", "4", "2"],
        ["ppo-continue", "0", "interactive", "idm", "normal", "2", "2"],
        ["ppo-continue", "1", "interactive", "idm", "normal", "4", "2"]]
    md = markdown_report(res)
    assert "- 1 of 2 runs evaluated on every task set" in md
    assert "| Anchor | 10.0 | 10.0 |" in md and "| PPO-Continue | 40.0 | 40.0 |" in md
    # Table III over the 4 pooled task-regimes: the anchor's 3 timeouts, 2 of them completed after
    assert "| Anchor (share) | 25.0 (1) | 75.0 (3) |" in md
    assert "| PPO-Continue | 100.0 | 66.7 |" in md


# ----------------------------------------------------------------------------- Ray
@pytest.mark.skipif(not ray_available(), reason="Ray is not installed (extra [cluster])")
def test_ray_backend_runs_each_run_as_a_task_and_writes_every_result(files, tmp_path):
    out = tmp_path / "out"
    doc = grid_doc(files, methods=["ppo-opponent"], seeds=[1], budget=200)
    result = run_experiment(doc, out, backend="ray", progress=False)
    assert result.backend == "ray" and result.ok, result.errors
    assert result.runs == {"anchor": "done", "ppo-opponent/seed1": "done"}
    for seed in (1,):
        folder = run_dir(out, RunSpec("ppo-opponent", seed))
        assert (folder / "eval_normal.npz").is_file() and (folder / "model.zip").is_file()
        assert json.loads((folder / "train.json").read_text())["b_post"] >= 200
    rows = (out / "results.csv").read_text().splitlines()[1:]
    assert {(r.split(",")[0], r.split(",")[1]) for r in rows} == {("anchor", ""), ("ppo-opponent", "1")}
    # the same grid again: everything is skipped without starting Ray work
    again = run_experiment(doc, out, backend="ray", progress=False)
    assert set(again.runs.values()) == {"skipped"}


def test_backend_errors(files, tmp_path):
    doc = grid_doc(files)
    with pytest.raises(GridError, match="backend: expected one of"):
        run_experiment(doc, tmp_path / "a", backend="spark", progress=False)
    with pytest.raises(GridError, match="address: a cluster address needs the Ray backend"):
        run_experiment(doc, tmp_path / "b", backend="sequential", address="auto", progress=False)


# ----------------------------------------------------------------------------- main job
def test_main_job_compares_both_methods_with_the_anchor_on_the_same_tasks(files, tmp_path):
    from cpalgo.experiments.mainjob import run_main_job

    out = tmp_path / "main"
    summary = run_main_job(anchor=files["anchor"], config=files["recipe"], out=str(out), budget=200, seed=3,
                           eval_tasks=1, progress=False)
    assert set(summary["policies"]) == {"anchor", "ppo-continue", "counterplay"}
    for policy in summary["policies"].values():
        assert set(policy) == {"interactive", "random"}
        assert set(policy["interactive"]) == {"score", "completion", "at_fault_collision", "timeout"}
    train = summary["training"]
    assert train["ppo-continue"]["b_post"] >= 200 and train["counterplay"]["b_post"] >= 200
    assert set(summary["repair"]) == {"ppo-continue", "counterplay"}
    grid = json.loads((out / "grid.json").read_text())["grid"]
    assert grid["seeds"] == [3] and grid["methods"] == ["ppo-continue", "counterplay"]
    assert len(grid["evaluation"]["regimes"]) == 8  # every traffic regime
    ev = {m: np.load(run_dir(out, RunSpec(m, None if m == "anchor" else 3)) / "eval_normal.npz")
          for m in ("anchor", "ppo-continue", "counterplay")}
    for m in ("ppo-continue", "counterplay"):  # the same held-out task-regimes for all three
        assert np.array_equal(ev[m]["scenario_id"], ev["anchor"]["scenario_id"])
        assert np.array_equal(ev[m]["regime"], ev["anchor"]["regime"])
    md = (out / "summary.md").read_text()
    assert "PPO-Continue" in md and "CounterPlay" in md and "Failure repair" in md
    assert "Retries by the first filter they failed: incomplete" in md
    for split in ("interactive", "random"):  # the paired difference, with its interval around it
        d = summary["difference"][split]
        scores = {m: summary["policies"][m][split]["score"] for m in ("counterplay", "ppo-continue")}
        assert d["mean"] == pytest.approx(scores["counterplay"] - scores["ppo-continue"])
        assert d["low"] <= d["mean"] <= d["high"]
        assert f"{d['mean']:+.2f} [{d['low']:+.2f}, {d['high']:+.2f}] ({split})" in md
