"""The main job (``counterplay run``): PPO-Continue and CounterPlay from the shipped anchor,
at the same B_post and seed, both against the anchor on the same held-out tasks.

Post-training more is itself a change; comparing CounterPlay with the anchor alone would
confound the method with training longer. So the job runs a two-method grid
(:mod:`cpalgo.experiments.runner`, in-process): PPO-Continue (factual self-play PPO) and
CounterPlay, one seed, the recipe's budget, then the BehaviorBench-style evaluator on the
Interactive and Random splits of held-out procedural tasks, all eight traffic regimes,
normal deployment. It writes the grid's files (``results.csv``, ``tables.md``, plots, the
runs' checkpoints under ``runs/``) and ``summary.md`` / ``summary.json``: score,
completion, at-fault collisions and timeouts per policy and split, the failure-repair table
and the search statistics. Like any grid it resumes when run again with the same ``--out``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from cpalgo.counterplay.search import ADMISSION_VERDICTS
from cpalgo.experiments.grid import ANCHOR, GridConfig, load_grid
from cpalgo.recipes import DEFAULT_ANCHOR, DEFAULT_POST_CONFIG

__all__ = ["main_job_grid", "run_main_job", "main_job_summary"]

METHODS = ("ppo-continue", "counterplay")


def main_job_grid(anchor: str, recipe: str, budget: int, seed: int = 0, eval_tasks: int = 50,
                  worlds: int | None = None, torch_threads: int = 1, scenarios: int | None = None) -> GridConfig:
    """The main job as a grid (validated like any grid file)."""
    doc: dict[str, Any] = {
        "name": "main job", "anchor": anchor, "recipe": recipe, "budget": int(budget), "seeds": [int(seed)],
        "methods": list(METHODS), "checkpoint_every": 2, "torch_threads": int(torch_threads),
        "evaluation": {"tasks": int(eval_tasks), "splits": ["interactive", "random"], "regimes": "all",
                       "deployments": ["normal"]},
        "description": "PPO-Continue and CounterPlay post-train the anchor at the same B_post and seed; "
                       "both and the anchor are evaluated on the same held-out tasks.",
    }
    if worlds:
        doc["worlds"] = int(worlds)
    if scenarios:
        doc["env"] = {"num_scenarios": int(scenarios)}
    return load_grid(doc)


def main_job_summary(out: str | os.PathLike, grid: GridConfig) -> dict[str, Any]:
    """``summary.md`` / ``summary.json`` of the main job from the grid's files."""
    from cpalgo.experiments.runs import write_json_atomic
    from cpalgo.experiments.tables import REPAIR_CLASSES, _cell, _paired, _repair_values, _table, collect_results
    from cpsim.atomic import write_bytes_atomic

    out = Path(out)
    res = collect_results(out, grid)
    dep = res.main_deployment
    policies = [m for m in (ANCHOR, *METHODS) if res.has(m, dep)]
    doc: dict[str, Any] = {"anchor": grid.anchor, "recipe": grid.recipe, "budget": grid.budget,
                           "seed": grid.seeds[0], "tasks_per_split": grid.evaluation.tasks,
                           "regimes": list(grid.evaluation.regimes), "policies": {}, "difference": {}, "repair": {},
                           "training": {}}
    lines = ["# Main job: PPO-Continue vs CounterPlay from the anchor", "",
             f"- anchor `{grid.anchor}`, recipe `{grid.recipe}`, B_post {grid.budget:,} live agent transitions "
             f"per method, seed {grid.seeds[0]}",
             f"- held-out procedural tasks: {grid.evaluation.tasks} per split, all "
             f"{len(grid.evaluation.regimes)} traffic regimes, {dep} deployment, argmax actions", ""]
    header = ["Policy", "split", "score", "completion %", "at-fault coll. %", "timeout %"]
    rows = []
    for m in policies:
        doc["policies"][m] = {}
        for split in res.splits:
            vals = {k: res.values(m, dep, split, "mean", k)
                    for k in ("score", "completion", "at_fault_collision", "timeout")}
            doc["policies"][m][split] = {k: (v[0] if v else None) for k, v in vals.items()}
            rows.append([res.label(m), split, _cell(vals["score"]), _cell(vals["completion"], 100.0),
                         _cell(vals["at_fault_collision"], 100.0), _cell(vals["timeout"], 100.0)])
    lines += ["Mean over the traffic regimes:", ""] + _table(header, rows)
    if all(res.has(m, dep) for m in METHODS):
        cells = []
        for split in res.splits:
            p = _paired(res, "counterplay", "ppo-continue", dep, split)
            if p is not None:
                doc["difference"][split] = {"mean": p[0], "low": p[1], "high": p[2]}
                cells.append(f"{p[0]:+.2f} [{p[1]:+.2f}, {p[2]:+.2f}] ({split})")
        if cells:
            lines += ["CounterPlay − PPO-Continue on the same task-regimes: " + ", ".join(cells) + "; 95 % "
                      "bootstrap interval over the tasks (one training seed each: seed noise is not in it, "
                      "see the paper grids for that).", ""]
    ref = res.evals.get((ANCHOR, None, dep))
    if ref is not None:
        import numpy as np

        from cpalgo.evaluate import metrics as M

        rows = []
        for split in res.splits:
            m = np.asarray(ref["split"]) == split
            classes = np.asarray(ref["outcome_class"])[m]
            shares = [f"{100 * np.mean(classes == int(M.OutcomeClass[n.upper()])):.1f}" for n, _ in REPAIR_CLASSES]
            rows.append([f"Anchor outcome share ({split})", *shares])
            for method in METHODS:
                vals = _repair_values(res, method, dep, split) if res.has(method, dep) else None
                if vals is None:
                    continue
                doc["repair"].setdefault(method, {})[split] = {n: (v[0] if v else None) for n, v in vals.items()}
                rows.append([f"{res.label(method)} repairs ({split})", *(_cell(vals[n], 100.0) for n, _ in REPAIR_CLASSES)])
        lines += ["Failure repair (%): share of each anchor outcome class that the policy completes without any "
                  "collision or off-road:", ""] + _table(["", *(t for _, t in REPAIR_CLASSES)], rows)
    for method in METHODS:
        t = res.train.get((method, grid.seeds[0]))
        if t is None:
            continue
        doc["training"][method] = {"b_post": t["b_post"], "generations": t["generations"], "wall_s": t["wall_s"],
                                   "budget": t["budget_totals"],
                                   "search": t.get("totals", {}).get("search_totals", {})}
    if "counterplay" in doc["training"]:
        s = doc["training"]["counterplay"]["search"]
        b = doc["training"]["counterplay"]["budget"]
        lines += [f"CounterPlay's search: {int(s.get('failures', 0))} failed tasks, {int(s.get('searches', 0))} "
                  f"searches, {int(s.get('admissible', 0))} admissible retries, {int(s.get('teachers_chosen', 0))} "
                  f"chosen, {int(s.get('verified', 0))} verified, {int(s.get('teachers', 0))} teachers distilled; "
                  f"branch share of B_post {100 * float(b.get('branch_share', 0)):.1f}%. Retries by the first "
                  "filter they failed: " + ", ".join(f"{v.replace('_', ' ')} {int(s.get(f'retries_{v}', 0))}"
                                                   for v in ADMISSION_VERDICTS) + ".", ""]
        files = res.train[("counterplay", grid.seeds[0])].get("search_files") or {}
        if files.get("figure") and Path(files["figure"]).is_file():  # one verified search, drawn
            write_bytes_atomic(out / "search.png", Path(files["figure"]).read_bytes())
            doc["search_figure"] = str(out / "search.png")
            lines += [f"A verified search: `search.png`; every kept search: `counterplay searches --model "
                      f"{files['searches']}`.", ""]
    for method, t in doc["training"].items():
        lines.append(f"- {res.label(method)}: B_post {t['b_post']:,} in {t['generations']} generations, "
                     f"{t['wall_s'] / 60:.1f} min")
    lines += ["", "Full tables: `tables.md`; per (method, seed, split, regime) rows: `results.csv`.", ""]
    write_bytes_atomic(out / "summary.md", "\n".join(lines).encode())
    write_json_atomic(out / "summary.json", doc)
    doc["markdown"] = "\n".join(lines)
    return doc


def run_main_job(anchor: str = DEFAULT_ANCHOR, config: str = DEFAULT_POST_CONFIG, out: str = "runs/counterplay",
                 budget: int | None = None, seed: int = 0, eval_tasks: int = 50, worlds: int | None = None,
                 torch_threads: int = 1, progress: bool = True, scenarios: int | None = None) -> dict[str, Any]:
    """Run the main job (see the module docstring); returns the summary dict (its
    ``markdown`` entry is ``summary.md``). ``budget`` defaults to the recipe's
    ``n_timesteps``; ``scenarios`` the training pool size (default: the recipe's).
    Raises ``ValueError`` naming the argument for a bad input."""
    from cpalgo.experiments.runner import run_experiment
    from cpalgo.recipes import load_recipe, resolve_path

    anchor = resolve_path(anchor)
    if not os.path.isfile(anchor):
        raise ValueError(f"anchor: no such checkpoint {anchor!r} (train one with `counterplay train-anchor`)")
    recipe_path = resolve_path(config)
    try:
        recipe = load_recipe(recipe_path)
    except ValueError as exc:
        raise ValueError(f"config: {exc}") from None
    grid = main_job_grid(anchor, recipe.path, budget or recipe.n_timesteps, seed, eval_tasks, worlds, torch_threads,
                         scenarios)
    t0 = time.perf_counter()
    result = run_experiment(grid, out, backend="sequential", progress=progress)
    summary = main_job_summary(out, grid)
    summary["wall_s"] = round(time.perf_counter() - t0, 1)
    summary["errors"] = result.errors
    if result.errors:
        raise RuntimeError("runs failed: " + "; ".join(f"{k}: {v}" for k, v in result.errors.items()))
    return summary


def _json(doc: Any) -> str:
    return json.dumps(doc, indent=2, default=str)
