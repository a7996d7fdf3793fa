"""The grid's results: ``results.csv``, ``tables.md`` in the seed paper's layouts, plots.

Inputs are the files the runs wrote (:mod:`cpalgo.experiments.runs`): ``eval_<deployment>.npz``
(per task-regime columns) and ``train.json`` of every run, and the anchor's evaluations.
A table is written only where the grid has its runs:

* **Table I**, per split: score per traffic regime and their mean, anchor and the
  ``baseline`` / ``counterplay`` methods, mean ± std over seeds (normal deployment), plus
  CounterPlay minus PPO-Continue.
* **Table II**, per split: the ``ablation`` methods with their components (B, C, S, D).
* **Table III**, per split: the anchor's outcome classes (share of task-regimes) and, for
  each main method, the share of each class it *repairs*: the ego reaches its goal without
  any collision or off-road (the seed paper's definition; co-player harm is reported in
  results.csv, not part of it).
* **Table IV**, per split: score and at-fault collision rate under every deployment
  condition the grid evaluates.
* **Style ceiling**, per split: of the task-regimes the anchor fails under the main
  deployment, the share the anchor itself completes cleanly under each other condition the
  grid evaluates it with, and the share PPO-Continue and CounterPlay repair; with the score
  of the best condition per task-regime, the most that choosing one driving style per task
  from the first decision could give.
* **Table V**, per split: the single-style panels (``panel`` methods) against CounterPlay:
  score, at-fault collision, off-road and goal rates.
* **Search statistics**: per CounterPlay-family method, failures, searches, admissible
  retries, verified share, teachers per generation and the branch share of B_post (plus
  the counters of the other methods: rewinds, opponent transitions, distillation teachers),
  and which filter each retry failed first (:func:`cpalgo.counterplay.search.admission_verdict`).
* **Paired differences**, per split: each method's score minus PPO-Continue's on the same
  task-regimes, and each ablation's and panel's minus CounterPlay's, with a 95 % bootstrap
  interval (:func:`paired_difference`) that resamples the tasks (shared by both methods) and
  each method's seeds.
* **Targets**: the seed paper's effects (CounterPlay >= 5 points above PPO-Continue, timeouts
  repaired, the ablations' order), each with its measured value and whether it holds.

Rates are percentages in the tables and in ``results.csv`` (columns ``*_pct``); scores
are 0-100; ``co_player_harm`` is other vehicles collided or off-road per task.

Several task sets (``evaluation.seed: [0, 1]``): ``results.csv`` gets a ``task_set`` column
(after ``deployment``) and a row per task set; the tables pool each run's task sets (their
task-regimes together: with equal task counts, the mean over the sets) and then report
mean ± std over the training seeds as with one set. A run counts in the tables only once it
is evaluated on every task set. With one task set both files are as they always were.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from cpalgo.counterplay.search import ADMISSION_VERDICTS
from cpalgo.evaluate import metrics as M
from cpalgo.experiments.grid import ANCHOR, GridConfig
from cpalgo.experiments.runs import eval_path, load_columns, run_dir
from cpsim.atomic import write_bytes_atomic
from cpsim.conditions import PANEL

__all__ = ["GridResults", "collect_results", "results_csv", "markdown_report", "write_tables", "repaired",
           "paired_difference", "RESULT_METRICS"]

#: results.csv metrics: (column, summarize key, scale)
RESULT_METRICS: tuple[tuple[str, str, float], ...] = (
    ("score", "score", 1.0),
    ("completion_pct", "completion", 100.0),
    ("at_fault_collision_pct", "at_fault_collision", 100.0),
    ("non_at_fault_collision_pct", "non_at_fault_collision", 100.0),
    ("offroad_pct", "offroad", 100.0),
    ("timeout_pct", "timeout", 100.0),
    ("co_player_harm", "co_player_harm", 1.0),
)
#: Table III's classes, in the paper's column order.
REPAIR_CLASSES: tuple[tuple[str, str], ...] = (
    ("completed", "Completed"), ("timeout", "Timeout"), ("at_fault_collision", "AF coll."),
    ("non_at_fault_collision", "Non-AF coll."), ("offroad", "Offroad"),
)
_SUMMARY_SOURCES = ("score", "goal", "at_fault_collision", "offroad", "non_at_fault_collision", "timeout",
                    "co_player_harm", "comfort", "lane_align", "lane_center")


#: bootstrap draws behind each paired difference's interval (a fixed generator seed keeps
#: ``tables.md`` reproducible)
PAIRED_DRAWS = 4000


def paired_difference(a: np.ndarray, b: np.ndarray, cluster: np.ndarray, *, draws: int = PAIRED_DRAWS,
                      level: float = 0.95, seed: int = 0) -> tuple[float, float, float]:
    """Mean score of method A minus method B's on the same rows, with a bootstrap interval.

    Args:
        a: (seeds_a, n) one value per training seed of A and row (task-regime).
        b: (seeds_b, n) B's values on the same n rows, in the same order.
        cluster: (n,) the task each row belongs to (any integer ids): a task's rows (its
            regimes) are drawn together, since they share the task's difficulty.
        draws, level, seed: bootstrap draws, the interval's coverage, the generator's seed.

    Each draw takes the tasks with replacement, the same for both methods (the comparison is
    paired, so a task's difficulty cancels), and each method's seeds with replacement (the
    training noise). With few seeds the seed part is underestimated (by (k-1)/k in variance
    for k seeds), so read an interval that barely excludes 0 with care.

    Returns:
        (difference of the means, interval low, interval high).
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    cluster = np.asarray(cluster).ravel()
    if a.ndim != 2 or b.ndim != 2 or not len(a) or not len(b):
        raise ValueError(f"paired_difference: a and b must be (seeds, rows) arrays with a seed each, "
                         f"got shapes {a.shape} and {b.shape}")
    if a.shape[1] != b.shape[1] or cluster.shape != (a.shape[1],) or not a.shape[1]:
        raise ValueError(f"paired_difference: a {a.shape}, b {b.shape} and cluster {cluster.shape} must "
                         "share a nonzero number of rows")
    if not 0.0 < level < 1.0:
        raise ValueError(f"paired_difference: level must lie in (0, 1), got {level}")
    ids = np.unique(cluster, return_inverse=True)[1].ravel()
    k = int(ids.max()) + 1
    count = np.bincount(ids, minlength=k).astype(np.float64)
    sums_a = np.stack([np.bincount(ids, weights=row, minlength=k) for row in a])
    sums_b = np.stack([np.bincount(ids, weights=row, minlength=k) for row in b])
    rng = np.random.default_rng(seed)
    weight = rng.multinomial(k, np.full(k, 1.0 / k), size=draws).astype(np.float64)  # (draws, k)
    pick_a = rng.integers(0, len(a), (draws, len(a)))
    pick_b = rng.integers(0, len(b), (draws, len(b)))
    per_task = sums_a[pick_a].mean(1) - sums_b[pick_b].mean(1)  # (draws, k) summed differences
    boot = (per_task * weight).sum(1) / (weight @ count)
    lo, hi = np.quantile(boot, [(1.0 - level) / 2, (1.0 + level) / 2])
    return float(a.mean() - b.mean()), float(lo), float(hi)


def repaired(columns: dict[str, np.ndarray]) -> np.ndarray:
    """(n,) bool: the ego reached its goal without any collision or off-road."""
    return (np.asarray(columns["goal"], bool) & ~np.asarray(columns["at_fault_collision"], bool)
            & ~np.asarray(columns["non_at_fault_collision"], bool) & ~np.asarray(columns["offroad"], bool))


@dataclass
class GridResults:
    """Everything the tables read.

    Attributes:
        grid: the grid.
        evals: (method, seed, deployment) -> columns; the anchor's seed is None. With
            several task sets: the columns of every task set, concatenated in the grid's
            order with a ``task_set`` column, for the runs evaluated on all of them.
        train: (method, seed) -> ``train.json``.
        summary: (method, seed, deployment, split, regime) -> :func:`metrics.summarize`;
            regime ``"mean"`` is the mean over the regimes.
        set_evals, set_summary: the same per task set (a last key element, the task set);
            filled only when the grid has several task sets.
    """

    grid: GridConfig
    evals: dict[tuple[str, int | None, str], dict[str, np.ndarray]] = field(default_factory=dict)
    train: dict[tuple[str, int], dict[str, Any]] = field(default_factory=dict)
    summary: dict[tuple[str, int | None, str, str, str], dict[str, float]] = field(default_factory=dict)
    set_evals: dict[tuple[str, int | None, str, int], dict[str, np.ndarray]] = field(default_factory=dict)
    set_summary: dict[tuple[str, int | None, str, str, str, int], dict[str, float]] = field(default_factory=dict)

    # ------------------------------------------------------------------ queries
    @property
    def splits(self) -> tuple[str, ...]:
        return self.grid.evaluation.splits

    @property
    def regimes(self) -> tuple[str, ...]:
        return self.grid.evaluation.regimes

    @property
    def task_sets(self) -> tuple[int, ...]:
        return self.grid.evaluation.task_sets

    @property
    def main_deployment(self) -> str:
        deps = list(self.grid.evaluation.deployments)
        return "normal" if "normal" in deps else deps[0]

    def seeds_of(self, method: str, deployment: str) -> list[int | None]:
        if method == ANCHOR:
            return [None] if (ANCHOR, None, deployment) in self.evals else []
        return [s for s in self.grid.seeds if (method, s, deployment) in self.evals]

    def has(self, method: str, deployment: str | None = None) -> bool:
        return bool(self.seeds_of(method, deployment or self.main_deployment))

    def values(self, method: str, deployment: str, split: str, regime: str, key: str) -> list[float]:
        """The metric of each seed (one value for the anchor)."""
        out = []
        for seed in self.seeds_of(method, deployment):
            s = self.summary.get((method, seed, deployment, split, regime))
            if s is not None and key in s:
                out.append(float(s[key]))
        return out

    def label(self, method: str) -> str:
        if method == ANCHOR:
            return "Anchor"
        from cpalgo.methods import get_method

        return get_method(method).row_label

    def methods_in(self, *groups: str) -> list[str]:
        from cpalgo.methods import get_method

        return [m for m in self.grid.methods if get_method(m).group in groups]


def _pooled(per_set: dict[int, dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The columns of several task sets as one evaluation (in the given order), plus the
    ``task_set`` of each row."""
    keys = [k for k in next(iter(per_set.values())) if all(k in cols for cols in per_set.values())]
    pooled = {k: np.concatenate([np.asarray(cols[k]) for cols in per_set.values()]) for k in keys}
    pooled["task_set"] = np.concatenate([np.full(np.asarray(cols["score"]).shape[0], t, np.int64)
                                         for t, cols in per_set.items()])
    return pooled


def _summaries(grid: GridConfig, cols: dict[str, np.ndarray]) -> dict[tuple[str, str], dict[str, float]]:
    """(split, regime) -> :func:`metrics.summarize` of one evaluation, regime ``"mean"``
    included where every regime of the grid was evaluated."""
    out: dict[tuple[str, str], dict[str, float]] = {}
    for split in grid.evaluation.splits:
        per_regime = []
        for regime in grid.evaluation.regimes:
            m = (cols["split"] == split) & (cols["regime"] == regime)
            if not m.any():
                continue
            s = M.summarize({k: np.asarray(cols[k])[m] for k in _SUMMARY_SOURCES if k in cols})
            out[(split, regime)] = s
            per_regime.append(s)
        # the regime mean only when every regime of the grid was evaluated: a mean over
        # fewer regimes would not be comparable with the other rows
        if per_regime and len(per_regime) == len(grid.evaluation.regimes):
            keys = [k for k in per_regime[0] if k != "n"]
            mean = {k: float(np.mean([p[k] for p in per_regime])) for k in keys}
            mean["n"] = sum(int(p["n"]) for p in per_regime)
            out[(split, "mean")] = mean
    return out


def collect_results(out: str | os.PathLike, grid: GridConfig) -> GridResults:
    """Read every evaluation and training summary the grid's runs wrote so far (with
    several task sets, a run's evaluations are pooled once it has all of them)."""
    res = GridResults(grid=grid)
    sets = grid.evaluation.task_sets
    for spec in grid.runs():
        folder = run_dir(out, spec)
        for deployment in grid.evaluation.deployments_of(spec.method):
            per_set = {t: load_columns(path) for t in sets
                       if (path := eval_path(grid, folder, deployment, t)).is_file()}
            if len(sets) == 1:
                if per_set:
                    res.evals[(spec.method, spec.seed, deployment)] = per_set[sets[0]]
                continue
            for t, cols in per_set.items():
                res.set_evals[(spec.method, spec.seed, deployment, t)] = cols
            if len(per_set) == len(sets):
                res.evals[(spec.method, spec.seed, deployment)] = _pooled(per_set)
        if spec.method != ANCHOR and (folder / "train.json").is_file():
            res.train[(spec.method, int(spec.seed))] = json.loads((folder / "train.json").read_text())
    for (method, seed, deployment), cols in res.evals.items():
        for (split, regime), s in _summaries(grid, cols).items():
            res.summary[(method, seed, deployment, split, regime)] = s
    for (method, seed, deployment, t), cols in res.set_evals.items():
        for (split, regime), s in _summaries(grid, cols).items():
            res.set_summary[(method, seed, deployment, split, regime, t)] = s
    return res


# ----------------------------------------------------------------------------- formatting
def _mean_std(values: Sequence[float]) -> tuple[float, float]:
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], np.float64)
    if v.size == 0:
        return float("nan"), float("nan")
    return float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else 0.0


def _cell(values: Sequence[float], scale: float = 1.0, decimals: int = 1) -> str:
    if not values:
        return "-"
    finite = [scale * x for x in values if x is not None and math.isfinite(x)]
    m, s = _mean_std(finite)
    if not math.isfinite(m):
        return "-"
    return f"{m:.{decimals}f}" + (f" ± {s:.{decimals}f}" if len(finite) > 1 else "")


def _table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines + [""]


def results_csv(res: GridResults) -> str:
    """One row per (method, seed, split, regime, deployment), and per task set (column
    ``task_set``) when the grid has several (see the module docstring)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    several = len(res.task_sets) > 1
    w.writerow(["method", "seed", "split", "regime", "deployment", *(["task_set"] if several else []), "n_tasks",
                *(c for c, _, _ in RESULT_METRICS)])
    order = [ANCHOR, *res.grid.methods]
    rows: dict[tuple, dict[str, float]] = dict(res.set_summary) if several else dict(res.summary)

    def sort_key(key: tuple) -> tuple:
        method, seed, deployment, split, regime = key[:5]
        return (order.index(method), -1 if seed is None else seed,
                list(res.grid.evaluation.deployments).index(deployment), res.splits.index(split),
                (list(res.regimes) + ["mean"]).index(regime), *(res.task_sets.index(t) for t in key[5:]))

    for key in sorted(rows, key=sort_key):
        method, seed, deployment, split, regime = key[:5]
        if regime == "mean":
            continue
        s = rows[key]
        w.writerow([method, "" if seed is None else seed, split, regime, deployment, *key[5:], int(s["n"]),
                    *(f"{scale * s.get(k, float('nan')):.4f}" for _, k, scale in RESULT_METRICS)])
    return buf.getvalue()


# ----------------------------------------------------------------------------- tables
def _table_i(res: GridResults, lines: list[str]) -> None:
    dep = res.main_deployment
    methods = [m for m in [ANCHOR, *res.methods_in("baseline", "counterplay")] if res.has(m, dep)]
    if len(methods) < 2:
        return
    lines += [f"## Table I: score per traffic regime ({dep} deployment)", ""]
    for split in res.splits:
        header = ["Method", *res.regimes, "Mean"]
        rows = [[res.label(m), *(_cell(res.values(m, dep, split, g, "score")) for g in (*res.regimes, "mean"))]
                for m in methods]
        if res.has("counterplay", dep) and res.has("ppo-continue", dep):
            diff = []
            for g in (*res.regimes, "mean"):
                a = _mean_std(res.values("counterplay", dep, split, g, "score"))[0]
                b = _mean_std(res.values("ppo-continue", dep, split, g, "score"))[0]
                diff.append(f"{a - b:+.1f}" if math.isfinite(a - b) else "-")
            rows.append(["CounterPlay − PPO-Continue", *diff])
        lines += [f"### {split.capitalize()} split ({_tasks_title(res, split)})", ""] + _table(header, rows)


def _n_tasks(res: GridResults, split: str) -> int:
    """Tasks of a split (over every task set: a task is a (task set, task) pair)."""
    for cols in res.evals.values():
        m = cols["split"] == split
        if m.any():
            task = np.asarray(cols["task"])[m]
            if "task_set" in cols:
                return len(set(zip(np.asarray(cols["task_set"])[m].tolist(), task.tolist())))
            return int(np.unique(task).size)
    return 0


def _tasks_title(res: GridResults, split: str) -> str:
    n = _n_tasks(res, split)
    sets = res.task_sets
    return f"{n} tasks" if len(sets) == 1 else f"{n} tasks over task sets {', '.join(map(str, sets))}, pooled"


def _table_ii(res: GridResults, lines: list[str]) -> None:
    dep = res.main_deployment
    ablations = [m for m in res.methods_in("ablation") if res.has(m, dep)]
    if not ablations:
        return
    from cpalgo.methods import get_method

    rows_methods = [m for m in [ANCHOR, "ppo-continue", *ablations, "counterplay"]
                    if (m == ANCHOR or m in res.grid.methods) and res.has(m, dep)]
    lines += [f"## Table II: component ablations ({dep} deployment, mean score over regimes)", "",
              "B: backtracking (value-guided, or decisions before the failure); C: search across styles; "
              "S: task-based selection and verification; D: teacher distillation.", ""]
    for split in res.splits:
        rows = []
        for m in rows_methods:
            comp = {} if m == ANCHOR else dict(get_method(m).components)
            rows.append([res.label(m), *(comp.get(k, "") for k in "BCSD"),
                         _cell(res.values(m, dep, split, "mean", "score"), decimals=2)])
        lines += [f"### {split.capitalize()} split", ""] + _table(["Variant", "B", "C", "S", "D", "Score"], rows)


def _repair_values(res: GridResults, method: str, dep: str, split: str) -> dict[str, list[float]] | None:
    ref = res.evals.get((ANCHOR, None, dep))
    if ref is None:
        return None
    out: dict[str, list[float]] = {name: [] for name, _ in REPAIR_CLASSES}
    for seed in res.seeds_of(method, dep):
        cols = res.evals[(method, seed, dep)]
        if not _same_tasks(ref, cols):
            return None  # not the same task-regimes: no repair analysis
        m = np.asarray(ref["split"]) == split
        ref_class = np.asarray(ref["outcome_class"])[m]
        ok = repaired(cols)[m]
        for name, _ in REPAIR_CLASSES:
            in_class = ref_class == int(M.OutcomeClass[name.upper()])
            if in_class.any():
                out[name].append(float(ok[in_class].mean()))
    return out


def _table_iii(res: GridResults, lines: list[str]) -> None:
    dep = res.main_deployment
    ref = res.evals.get((ANCHOR, None, dep))
    methods = [m for m in res.methods_in("baseline", "counterplay") if res.has(m, dep)]
    if ref is None or not methods:
        return
    lines += [f"## Table III: task retention and failure repair ({dep} deployment, %)", "",
              "Anchor rows: the anchor's outcome classes over all task-regimes (priority at-fault collision > "
              "off-road > completed > non-at-fault collision > timeout). Method rows: the share of each anchor "
              "class the method completes without any collision or off-road (mean ± std over seeds).", ""]
    for split in res.splits:
        m = np.asarray(ref["split"]) == split
        classes = np.asarray(ref["outcome_class"])[m]
        header = ["Policy", *(title for _, title in REPAIR_CLASSES)]
        counts = {n: int(np.sum(classes == int(M.OutcomeClass[n.upper()]))) for n, _ in REPAIR_CLASSES}
        rows = [["Anchor (share)", *(f"{100 * counts[n] / max(classes.size, 1):.1f} ({counts[n]})"
                                     for n, _ in REPAIR_CLASSES)]]
        for method in methods:
            vals = _repair_values(res, method, dep, split)
            if vals is None:  # said in the table, not dropped silently
                rows.append([res.label(method) + " (tasks differ from the anchor's: no repair analysis)",
                             *("-" for _ in REPAIR_CLASSES)])
                continue
            rows.append([res.label(method), *(_cell(vals[n], 100.0) for n, _ in REPAIR_CLASSES)])
        lines += [f"### {split.capitalize()} split ({int(m.sum())} task-regimes)", ""] + _table(header, rows)


def _table_iv(res: GridResults, lines: list[str]) -> None:
    deps = [d for d in res.grid.evaluation.deployments if any(
        res.has(m, d) for m in res.grid.methods)]
    if len(deps) < 2:
        return
    candidates = [ANCHOR, "ppo-continue", *res.methods_in("distillation"), "counterplay"]
    methods = [m for m in candidates if (m == ANCHOR or m in res.grid.methods) and sum(res.has(m, d) for d in deps) >= 2]
    if not methods:
        return
    lines += ["## Table IV: deployment conditions (score, at-fault collision %)", "",
              "Every condition uses the same goal criterion; the condition changes the ego's style fields only.", ""]
    for split in res.splits:
        header = ["Method"] + [f"{d} {what}" for d in deps for what in ("score", "AF-C %")]
        rows = []
        for m in methods:
            row = [res.label(m)]
            for d in deps:
                row += [_cell(res.values(m, d, split, "mean", "score"), decimals=2),
                        _cell(res.values(m, d, split, "mean", "at_fault_collision"), 100.0, 2)]
            rows.append(row)
        lines += [f"### {split.capitalize()} split", ""] + _table(header, rows)


def _same_tasks(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    keys = ("split", "regime", "scenario_id", "ego") + (("task_set",) if "task_set" in a else ())
    return all(k in b and np.array_equal(np.asarray(a[k]), np.asarray(b[k])) for k in keys)


def _share_of(ok: np.ndarray, among: np.ndarray) -> str:
    """Percent of the rows ``among`` marks that ``ok`` marks ('-' when there are none)."""
    return f"{100 * ok[among].mean():.1f}" if among.any() else "-"


def _style_ceiling(res: GridResults, lines: list[str]) -> None:
    dep = res.main_deployment
    ref = res.evals.get((ANCHOR, None, dep))
    if ref is None:
        return
    others = [d for d in res.grid.evaluation.deployments if d != dep and (ANCHOR, None, d) in res.evals
              and _same_tasks(ref, res.evals[(ANCHOR, None, d)])]
    if not others:
        return
    fixed = {d: repaired(res.evals[(ANCHOR, None, d)]) for d in others}
    any_fixed = np.logical_or.reduce(list(fixed.values()))
    methods = [m for m in ("ppo-continue", "counterplay") if m in res.grid.methods and res.has(m, dep)]
    lines += ["## Style ceiling: the anchor's failures another deployment condition repairs", "",
              f"Over the task-regimes the anchor does not complete cleanly under {dep} deployment: the share "
              "the anchor itself completes without any collision or off-road under each other condition "
              "(same task-regimes, the condition held from the first decision) or under any of them, and the "
              f"share each method repairs under {dep} deployment (mean ± std over seeds). Best condition per "
              "task: the mean over task-regimes of the anchor's highest score over its conditions, what a "
              "policy that picked one condition per task knowing the outcomes would score.", ""]
    header = ["Split", "anchor failures", *(f"{d} %" for d in others), "any condition %",
              *(f"{res.label(m)} %" for m in methods), f"score, {dep}", "score, best condition per task"]
    rows = []
    for split in res.splits:
        m = np.asarray(ref["split"]) == split
        failed = m & ~repaired(ref)
        if not m.any():
            continue
        n = int(failed.sum())
        method_cells = []
        for method in methods:
            vals = [float(repaired(res.evals[(method, s, dep)])[failed].mean()) for s in res.seeds_of(method, dep)
                    if n and _same_tasks(ref, res.evals[(method, s, dep)])]
            method_cells.append(_cell(vals, 100.0))
        best = np.max([np.asarray(res.evals[(ANCHOR, None, d)]["score"], np.float64)[m] for d in (dep, *others)], axis=0)
        rows.append([split, f"{n} of {int(m.sum())}", *(_share_of(fixed[d], failed) for d in others),
                     _share_of(any_fixed, failed),
                     *method_cells, f"{np.asarray(ref['score'], np.float64)[m].mean():.1f}", f"{best.mean():.1f}"])
    lines += _table(header, rows)


def _table_v(res: GridResults, lines: list[str]) -> None:
    dep = res.main_deployment
    panels = [m for m in res.methods_in("panel") if res.has(m, dep)]
    if not panels:
        return
    methods = (["counterplay"] if res.has("counterplay", dep) else []) + panels
    lines += [f"## Table V: search with one or five driving styles ({dep} deployment)", "",
              "Each search runs five candidate retries; single-style panels draw the focal agent's actions "
              "independently per branch (co-players shared). Rates in % over all regimes.", ""]
    for split in res.splits:
        rows = []
        for m in methods:
            label = "All five styles (CounterPlay)" if m == "counterplay" else res.label(m)
            rows.append([label, _cell(res.values(m, dep, split, "mean", "score"), decimals=2),
                         _cell(res.values(m, dep, split, "mean", "at_fault_collision"), 100.0, 2),
                         _cell(res.values(m, dep, split, "mean", "offroad"), 100.0, 2),
                         _cell(res.values(m, dep, split, "mean", "completion"), 100.0, 1)])
        lines += [f"### {split.capitalize()} split", ""] + _table(["Search styles", "Score", "AF-C %", "Off. %", "Goal %"], rows)


def _per_seed(res: GridResults, method: str, fn: Any) -> list[float]:
    out = []
    for seed in res.grid.seeds:
        t = res.train.get((method, seed))
        if t is None:
            continue
        try:
            v = fn(t)
        except (KeyError, ZeroDivisionError, TypeError):
            continue
        if v is not None and math.isfinite(v):
            out.append(float(v))
    return out


def _search_table(res: GridResults, lines: list[str]) -> None:
    family = [m for m in res.grid.methods if any((m, s) in res.train for s in res.grid.seeds)]
    if not family:
        return
    cp = [m for m in family if m in res.methods_in("counterplay", "ablation", "panel")]
    lines += ["## Search statistics and budget", ""]
    if cp:
        def st(t: dict, key: str) -> float:
            return float(t["totals"]["search_totals"].get(key, 0))

        rows = []
        for m in cp:
            rows.append([
                res.label(m),
                _cell(_per_seed(res, m, lambda t: st(t, "failures") / t["generations"]), decimals=1),
                _cell(_per_seed(res, m, lambda t: st(t, "searches") / t["generations"]), decimals=1),
                _cell(_per_seed(res, m, lambda t: st(t, "teachers_chosen") / st(t, "searches")), 100.0),
                _cell(_per_seed(res, m, lambda t: st(t, "admissible") / st(t, "searches")), decimals=2),
                _cell(_per_seed(res, m, lambda t: st(t, "verified") / st(t, "teachers_chosen")), 100.0),
                _cell(_per_seed(res, m, lambda t: st(t, "teachers") / t["generations"]), decimals=2),
                _cell(_per_seed(res, m, lambda t: t["budget_totals"]["branch_share"]), 100.0),
            ])
        lines += ["Per generation; admissible share: searches whose chosen retry passed the filters (with "
                  "selection by reward, searches with a chosen retry); verified share: chosen retries that "
                  "passed the rerun; branch share: branch transitions / B_post.", ""]
        lines += _table(["Method", "failures/gen", "searches/gen", "admissible share %",
                         "admissible retries/search", "verified share %", "teachers/gen", "branch share %"], rows)
        def share(t: dict, name: str) -> float:
            return st(t, f"retries_{name}") / sum(st(t, f"retries_{v}") for v in ADMISSION_VERDICTS)

        verdict_rows = []
        for m in cp:
            verdict_rows.append([res.label(m)] + [_cell(_per_seed(res, m, lambda t, v=v: share(t, v)), 100.0)
                                                  for v in ADMISSION_VERDICTS]
                                + [_cell(_per_seed(res, m, lambda t: st(t, "factual_completed") / st(t, "searches")), 100.0)])
        if any(any(c != "-" for c in row[1:1 + len(ADMISSION_VERDICTS)]) for row in verdict_rows):
            lines += ["Which filter each retry failed (% of retries, first failing filter; runs that recorded it): "
                      "incomplete: did not complete the task; not better: completed but did not outrank the "
                      "factual branch; harms other: a new or earlier collision / off-road of another vehicle. "
                      "Factual completed: searches whose factual branch completed (% of searches).", ""]
            lines += _table(["Method", "incomplete %", "not better %", "harms other %", "admitted %",
                             "factual completed %"], verdict_rows)
        _roots_and_styles(res, cp, st, lines)
    other = []
    for m in family:
        if m in cp:
            continue
        t = next((res.train[(m, s)] for s in res.grid.seeds if (m, s) in res.train), None)
        if t is None:
            continue
        counters = {name: vals for name, vals in t.get("totals", {}).items() if name != "search_totals" and vals}
        desc = "; ".join(f"{k} {_cell(_per_seed(res, m, lambda t, n=name, k=k: t['totals'][n][k] / t['generations']), decimals=1)}/gen"
                         for name, vals in counters.items() for k in sorted(vals))
        other.append([res.label(m), _cell(_per_seed(res, m, lambda t: t["b_post"]), decimals=0),
                      _cell(_per_seed(res, m, lambda t: t["generations"]), decimals=1), desc or "-"])
    if other:
        lines += _table(["Method", "B_post", "generations", "counters"], other)
    walls = [(res.label(m), _cell(_per_seed(res, m, lambda t: t["wall_s"] / 60), decimals=1),
              _cell(_per_seed(res, m, lambda t: t["b_post"]), decimals=0)) for m in family]
    if walls:
        lines += ["Training wall time (min) and B_post reached per run:", ""]
        lines += _table(["Method", "wall min", "B_post"], walls)


def _roots_and_styles(res: GridResults, cp: list[str], st: Any, lines: list[str]) -> None:
    """Where the searched roots lie (decisions before the failure) and which driving style the
    verified teachers drove, from the runs' ``root_depth_<d>`` and ``profile_<name>`` counters."""
    def depth_share(t: dict, lo: int, hi: int) -> float:
        depths = {int(k[len("root_depth_"):]): v for k, v in t["totals"]["search_totals"].items()
                  if k.startswith("root_depth_") and k != "root_depth_sum"}
        n = sum(depths.values())
        return sum(v for d, v in depths.items() if lo <= d <= hi) / n if n else math.nan

    def style_share(t: dict, name: str) -> float:
        n = st(t, "teachers")
        return st(t, f"profile_{name}") / n if n else math.nan

    rows = []
    for m in cp:
        rows.append([res.label(m),
                     _cell(_per_seed(res, m, lambda t: st(t, "failures_timeout") / st(t, "failures")), 100.0),
                     _cell(_per_seed(res, m, lambda t: st(t, "root_depth_sum") / st(t, "searches")), decimals=1),
                     _cell(_per_seed(res, m, lambda t: depth_share(t, 0, 9)), 100.0),
                     _cell(_per_seed(res, m, lambda t: depth_share(t, 55, 10**9)), 100.0)]
                    + [_cell(_per_seed(res, m, lambda t, p=p: style_share(t, p)), 100.0) for p in PANEL]
                    + ["-"])
    if not any(row[2] != "-" for row in rows):
        return
    for m, row in zip(cp, rows):  # teachers that kept w0 counted by panel slot are no style's
        if not _changes_style(m):
            teachers = sum(_per_seed(res, m, lambda t: st(t, "teachers")))
            row[5:] = ["-"] * len(PANEL) + ["100.0" if teachers else "-"]
    lines += ["Where the roots lie and which styles win: timeouts as a share of the failures; the searched "
              "roots' depth in decisions before the failure (mean; share among the nearest roots, under 10; "
              "share at the window's far edge, 55 or more); the driving style of the verified teachers "
              "(% of teachers; own: the focal agent's own condition w0, kept without a style change).", ""]
    lines += _table(["Method", "timeouts % of failures", "root depth", "nearest roots %", "far edge %"]
                    + [f"{p} %" for p in PANEL] + ["own %"], rows)


def _changes_style(method: str) -> bool:
    from cpalgo.methods import get_method

    try:
        return bool(get_method(method).settings.get("style_change", True))
    except ValueError:  # a method this install does not register
        return True


def _paired(res: GridResults, method: str, ref: str, dep: str, split: str) -> tuple[float, float, float] | None:
    """:func:`paired_difference` of ``method`` minus ``ref`` on ``split`` (None when a run of
    either was evaluated on other task-regimes than the others)."""
    runs = [res.evals[(m, s, dep)] for m in (method, ref) for s in res.seeds_of(m, dep)]
    if not runs or not all(_same_tasks(runs[0], cols) for cols in runs[1:]):
        return None
    first = runs[0]
    rows = np.asarray(first["split"]) == split
    if not rows.any():
        return None
    task = np.asarray(first["task"])[rows]
    task_set = np.asarray(first["task_set"])[rows] if "task_set" in first else np.zeros_like(task)
    cluster = np.unique(np.stack([task_set, task], 1), axis=0, return_inverse=True)[1].ravel()
    n_a = len(res.seeds_of(method, dep))
    scores = [np.asarray(cols["score"], np.float64)[rows] for cols in runs]
    return paired_difference(np.stack(scores[:n_a]), np.stack(scores[n_a:]), cluster)


def _paired_table(res: GridResults, lines: list[str]) -> None:
    """Every method against PPO-Continue; the CounterPlay variants (ablations, single-style
    panels) also against CounterPlay, the comparison Tables II and V make."""
    dep = res.main_deployment
    against = (("ppo-continue", [ANCHOR, *res.grid.methods]),
               ("counterplay", res.methods_in("ablation", "panel")))
    for ref, candidates in against:
        if ref not in res.grid.methods or not res.has(ref, dep):
            continue
        methods = [m for m in candidates if m != ref and res.has(m, dep)]
        if not methods:
            continue
        rows = []
        for m in methods:
            cells = []
            for split in res.splits:
                p = _paired(res, m, ref, dep, split)
                cells.append("tasks differ" if p is None else f"{p[0]:+.2f} [{p[1]:+.2f}, {p[2]:+.2f}]")
            rows.append([res.label(m), str(len(res.seeds_of(m, dep))), *cells])
        name = res.label(ref)
        lines += [f"## Paired differences from {name} ({dep} deployment, score)", "",
                  f"Mean score minus {name}'s ({len(res.seeds_of(ref, dep))} seeds) on the same task-regimes "
                  f"[95 % bootstrap interval, {PAIRED_DRAWS} draws that resample the tasks, the same for both "
                  "methods, and each method's seeds]. An interval that excludes 0 separates the two beyond "
                  "task and seed noise; with three seeds the seed part is underestimated.", ""]
        lines += _table(["Method", "Seeds", *(f"{s.capitalize()}" for s in res.splits)], rows)


def _targets(res: GridResults, lines: list[str]) -> None:
    dep = res.main_deployment
    checks = []
    if res.has("counterplay", dep) and res.has("ppo-continue", dep):
        for split in res.splits:
            cp = res.values("counterplay", dep, split, "mean", "score")
            pc = res.values("ppo-continue", dep, split, "mean", "score")
            d = _mean_std(cp)[0] - _mean_std(pc)[0]
            p = _paired(res, "counterplay", "ppo-continue", dep, split)
            interval = "" if p is None else f" [95 % interval {p[1]:+.2f}, {p[2]:+.2f}]"
            checks.append((f"CounterPlay − PPO-Continue, {split}: >= +5 points",
                           f"{d:+.2f}{interval} (CounterPlay {_cell(cp, decimals=2)}, "
                           f"PPO-Continue {_cell(pc, decimals=2)})", d >= 5.0))
        for split in res.splits:
            cpv = _repair_values(res, "counterplay", dep, split)
            pcv = _repair_values(res, "ppo-continue", dep, split)
            if cpv and pcv and cpv["timeout"] and pcv["timeout"]:
                a, b = _mean_std(cpv["timeout"])[0] * 100, _mean_std(pcv["timeout"])[0] * 100
                checks.append((f"timeouts repaired, {split}: CounterPlay >= 30%, PPO-Continue <= 10%",
                               f"{a:.1f}% vs {b:.1f}%", a >= 30.0 and b <= 10.0))
    variants = [m for m in ["counterplay", *res.methods_in("ablation")] if res.has(m, dep)]
    if "counterplay" in variants and "cp-no-style" in variants:
        for split in res.splits:
            scores = {m: _mean_std(res.values(m, dep, split, "mean", "score"))[0] for m in variants}
            best, worst = max(scores, key=scores.get), min(scores, key=scores.get)
            checks.append((f"Table II shape, {split}: full method highest, cp-no-style lowest of the variants",
                           f"highest {best} ({scores[best]:.2f}), lowest {worst} ({scores[worst]:.2f})",
                           best == "counterplay" and worst == "cp-no-style"))
    if res.has("counterplay", dep) and res.has("distill-aggressive", dep):
        for split in res.splits:
            (cs, _), (ds, _) = (_mean_std(res.values(m, dep, split, "mean", "score"))
                                for m in ("counterplay", "distill-aggressive"))
            (cf, _), (df, _) = (_mean_std(res.values(m, dep, split, "mean", "at_fault_collision"))
                                for m in ("counterplay", "distill-aggressive"))
            checks.append((f"Table IV, {split}: CounterPlay above the aggressive distillation control, "
                           "at no higher at-fault collision rate",
                           f"{cs:.2f} at {100 * cf:.2f}% vs {ds:.2f} at {100 * df:.2f}%", cs > ds and cf <= df))
    teachers = _per_seed(res, "counterplay", lambda t: t["totals"]["search_totals"]["teachers"] / t["generations"])
    if teachers:
        per_gen = _mean_std(teachers)[0]
        checks.append(("verified teachers per generation (CounterPlay) >= 10", f"{per_gen:.2f}", per_gen >= 10.0))
    if not checks:
        return
    lines += ["## Targets (the seed paper's effects)", ""]
    lines += _table(["Target", "Measured", "Met"], [[t, v, "yes" if ok else "**no**"] for t, v, ok in checks])


def markdown_report(res: GridResults, extra: str = "") -> str:
    """``tables.md``: the tables the grid has runs for (see the module docstring)."""
    g = res.grid
    e = g.evaluation
    n_done = len({(m, s) for (m, s, _d) in res.evals if m != ANCHOR})
    sets = e.task_sets
    pool = (f"pool {e.pool} (seed {e.seed})" if len(sets) == 1 else
            f"pool {e.pool} ({len(sets)} task sets: seeds {', '.join(map(str, sets))})")
    lines = [f"# Grid {g.name}", "",
             f"- anchor `{g.anchor}`, recipe `{g.recipe}`, B_post {g.budget:,} live agent transitions per run, "
             f"seeds {list(g.seeds)}",
             f"- evaluation: {e.tasks} tasks per split ({', '.join(e.splits)}), regimes {', '.join(e.regimes)}, "
             f"{pool}; deployments " + "; ".join(
                 f"{d}: {len(ms)} policies" for d, ms in e.deployments.items()),
             f"- {n_done} of {len(g.methods) * len(g.seeds)} runs evaluated"
             + ("" if len(sets) == 1 else " on every task set"),
             "- a ± b: mean and sample standard deviation (n − 1) over the seeds that have the run", ""]
    if len(sets) > 1:
        lines[-1:-1] = ["- each run's numbers pool its task sets (their task-regimes together: with equal task "
                        "counts, the mean over the sets); results.csv has a row per task set"]
    if g.description:
        lines += [g.description.strip(), ""]
    if extra:
        lines += [extra.strip(), ""]
    for part in (_table_i, _table_ii, _table_iii, _table_iv, _style_ceiling, _table_v, _search_table,
                 _paired_table, _targets):
        part(res, lines)
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- plots
def _plots(res: GridResults, out: Path) -> list[str]:
    try:
        import matplotlib

        matplotlib.use("Agg", force=False)
        from matplotlib.figure import Figure
    except ImportError:
        return []
    from cpsim.atomic import atomic_path

    written = []
    dep = res.main_deployment
    methods = [m for m in [ANCHOR, *res.methods_in("baseline", "counterplay")] if res.has(m, dep)]
    if methods:
        fig = Figure(figsize=(max(8, 1.3 * (len(res.regimes) + 1)), 3.6 * len(res.splits)))
        axes = fig.subplots(len(res.splits), 1, squeeze=False)[:, 0]
        cols = [*res.regimes, "mean"]
        width = 0.8 / len(methods)
        for ax, split in zip(axes, res.splits):
            for i, m in enumerate(methods):
                stats = [_mean_std(res.values(m, dep, split, g, "score")) for g in cols]
                x = np.arange(len(cols)) + (i - (len(methods) - 1) / 2) * width
                ax.bar(x, [s[0] for s in stats], width, yerr=[s[1] for s in stats], label=res.label(m), capsize=2)
            ax.set_xticks(np.arange(len(cols)), cols)
            ax.set_ylabel("score (0-100)")
            ax.set_title(f"{split} split, {dep} deployment")
        axes[0].legend(fontsize=8, ncol=min(len(methods), 4))
        fig.tight_layout()
        with atomic_path(out / "scores.png", suffix=".png") as tmp:
            fig.savefig(tmp, dpi=110)
        written.append("scores.png")
    rep_methods = [m for m in res.methods_in("baseline", "counterplay") if res.has(m, dep)]
    if (ANCHOR, None, dep) in res.evals and rep_methods:
        fig = Figure(figsize=(9, 3.4 * len(res.splits)))
        axes = fig.subplots(len(res.splits), 1, squeeze=False)[:, 0]
        width = 0.8 / len(rep_methods)
        for ax, split in zip(axes, res.splits):
            for i, m in enumerate(rep_methods):
                vals = _repair_values(res, m, dep, split) or {}
                stats = [_mean_std([100 * v for v in vals.get(n, [])]) for n, _ in REPAIR_CLASSES]
                x = np.arange(len(REPAIR_CLASSES)) + (i - (len(rep_methods) - 1) / 2) * width
                ax.bar(x, [s[0] for s in stats], width, yerr=[s[1] for s in stats], label=res.label(m), capsize=2)
            ax.set_xticks(np.arange(len(REPAIR_CLASSES)), [f"anchor: {t}" for _, t in REPAIR_CLASSES], fontsize=8)
            ax.set_ylabel("repaired (%)")
            ax.set_title(f"{split} split: share of each anchor outcome class completed cleanly")
        axes[0].legend(fontsize=8)
        fig.tight_layout()
        with atomic_path(out / "repair.png", suffix=".png") as tmp:
            fig.savefig(tmp, dpi=110)
        written.append("repair.png")
    return written


def write_tables(out: str | os.PathLike, grid: GridConfig, extra: str = "") -> list[str]:
    """Write ``results.csv``, ``tables.md`` and the plots into ``out``; returns the file names."""
    out = Path(out)
    res = collect_results(out, grid)
    written = []
    write_bytes_atomic(out / "results.csv", results_csv(res).encode())
    written.append("results.csv")
    figures = _plots(res, out)
    md = markdown_report(res, extra)
    md += "".join(f"\n![{name}]({name})\n" for name in figures)
    write_bytes_atomic(out / "tables.md", md.encode())
    written.append("tables.md")
    return written + figures
