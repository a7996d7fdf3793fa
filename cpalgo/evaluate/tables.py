"""Aggregation, Markdown tables (seed-paper layout), JSON and CSV, written atomically.

Input: a list of :class:`cpalgo.evaluate.runner.EvalResult` (one per evaluated
checkpoint). Results that share a ``label`` are checkpoints (seeds) of one policy: the
tables report their mean and, with more than one, the standard deviation.

Layout of the Markdown tables (the seed paper's): one table per split and metric,
traffic regimes as columns plus their mean, policies as rows.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from typing import TYPE_CHECKING, Any, Iterable, Mapping, Sequence

import numpy as np

from cpalgo.evaluate import metrics as M
from cpsim.atomic import AtomicDir, write_text_atomic

if TYPE_CHECKING:  # pragma: no cover
    from cpalgo.evaluate.runner import EvalResult

#: Metrics aggregated per (policy, split, regime), with how tables show them.
SUMMARY_METRICS: tuple[str, ...] = (
    "score", "completion", "at_fault_collision", "offroad", "non_at_fault_collision", "timeout",
    "co_player_harm", "comfort", "lane_align", "lane_center",
)
#: Metrics printed as Markdown tables: (key, title, scale, decimals).
TABLE_METRICS: tuple[tuple[str, str, float, int], ...] = (
    ("score", "Score (0-100)", 1.0, 1),
    ("completion", "Completion (%)", 100.0, 1),
    ("at_fault_collision", "At-fault collision (%)", 100.0, 1),
    ("offroad", "Off-road (%)", 100.0, 1),
    ("co_player_harm", "Co-player harm (other vehicles collided or off-road per task)", 1.0, 2),
)
#: Per-task columns written to tasks.csv, in order.
TASK_COLUMNS: tuple[str, ...] = (
    "split", "regime", "task", "scenario_id", "ego", "goal", "at_fault_collision",
    "non_at_fault_collision", "offroad", "timeout", "outcome_class", "comfort", "lane_align",
    "lane_center", "score", "co_player_harm", "steps_alive", "goal_step",
)


# ----------------------------------------------------------------------------- aggregation
def _mean_std(values: Sequence[float]) -> dict[str, Any]:
    v = np.asarray([x for x in values], np.float64)
    finite = v[np.isfinite(v)]
    return {
        "mean": float(finite.mean()) if finite.size else float("nan"),
        "std": float(finite.std(ddof=1)) if finite.size > 1 else 0.0,
        "values": [float(x) for x in v],
    }


def _group_by_label(results: Sequence["EvalResult"]) -> dict[str, list["EvalResult"]]:
    groups: dict[str, list[EvalResult]] = {}
    for r in results:
        groups.setdefault(r.label, []).append(r)
    return groups


def _ordered_unique(values: Iterable[str]) -> list[str]:
    seen: dict[str, None] = {}
    for v in values:
        seen.setdefault(str(v), None)
    return list(seen)


def summarize_results(results: Sequence["EvalResult"]) -> dict[str, Any]:
    """Per policy label, split and regime: every metric of :data:`SUMMARY_METRICS` as
    ``{"mean", "std", "values"}`` across checkpoints, plus ``mean_over_regimes`` (the
    mean over regimes per checkpoint, then mean/std across checkpoints).

    Returns a JSON-serialisable dict: ``{"splits", "regimes", "policies": {label:
    {"checkpoints": [...], "splits": {split: {"regimes": {regime: {metric: stats}},
    "mean_over_regimes": {metric: stats}}}}}}``.
    """
    if not results:
        raise ValueError("results: nothing to summarise")
    splits = _ordered_unique(s for r in results for s in r.columns["split"])
    regimes = _ordered_unique(g for r in results for g in r.columns["regime"])
    policies: dict[str, Any] = {}
    for label, group in _group_by_label(results).items():
        per_split: dict[str, Any] = {}
        for split in splits:
            # per checkpoint: {regime: summary}
            per_ckpt: list[dict[str, dict[str, float]]] = []
            for r in group:
                cols = r.columns
                in_split = cols["split"] == split
                ck: dict[str, dict[str, float]] = {}
                for regime in regimes:
                    m = in_split & (cols["regime"] == regime)
                    if m.any():
                        ck[regime] = M.summarize({k: np.asarray(cols[k])[m] for k in SUMMARY_METRICS_SOURCES
                                                  if k in cols})
                per_ckpt.append(ck)
            present = [g for g in regimes if all(g in ck for ck in per_ckpt)]
            if not present:
                continue
            reg_stats = {
                g: {k: _mean_std([ck[g].get(k, float("nan")) for ck in per_ckpt])
                    for k in SUMMARY_METRICS if k in per_ckpt[0][g]}
                for g in present
            }
            over = {
                k: _mean_std([float(np.nanmean([ck[g].get(k, float("nan")) for g in present]))
                              for ck in per_ckpt])
                for k in SUMMARY_METRICS if k in per_ckpt[0][present[0]]
            }
            per_split[split] = {"regimes": reg_stats, "mean_over_regimes": over,
                                "n_tasks": int(per_ckpt[0][present[0]]["n"])}
        policies[label] = {"checkpoints": [r.checkpoint for r in group], "splits": per_split}
    return {"splits": splits, "regimes": regimes, "policies": policies}


# Per-task columns summarize() reads (names as in the runner's columns).
SUMMARY_METRICS_SOURCES: tuple[str, ...] = (
    "score", "goal", "at_fault_collision", "offroad", "non_at_fault_collision", "timeout",
    "co_player_harm", "comfort", "lane_align", "lane_center",
)


def outcome_analysis(reference: "EvalResult", other: "EvalResult") -> dict[str, Any]:
    """The seed paper's failure-repair table: the reference policy's outcome classes over
    all task-regimes, and for each class the share the other policy repairs (the seed
    paper's repair: its ego reaches the goal without any collision or off-road event,
    :func:`metrics.repaired`) and, in its own column, the share in which the other policy
    harmed a co-player (``"harm"``; not part of the repair).

    Both results must cover the same task-regimes in the same order.
    """
    keys = ("split", "regime", "scenario_id", "ego")
    for k in keys:
        if not np.array_equal(np.asarray(reference.columns[k]), np.asarray(other.columns[k])):
            raise ValueError(f"outcome_analysis: results differ in their task-regimes (column {k!r}); "
                             "evaluate both policies on the same tasks and regimes")
    o = other.columns
    repaired = M.repaired(o["goal"], o["at_fault_collision"], o["non_at_fault_collision"], o["offroad"])
    table = M.repair_table(reference.columns["outcome_class"], repaired, o["co_player_harm"])
    return {"reference": reference.label, "other": other.label, "classes": table,
            "n": int(np.asarray(reference.columns["outcome_class"]).size)}


# ----------------------------------------------------------------------------- formatting
def _fmt(stats: Mapping[str, Any] | None, scale: float, decimals: int) -> str:
    if stats is None or not math.isfinite(stats["mean"]):
        return "-"
    s = f"{stats['mean'] * scale:.{decimals}f}"
    if len(stats["values"]) > 1:
        s += f" ± {stats['std'] * scale:.{decimals}f}"
    return s


def markdown_tables(summary: Mapping[str, Any],
                    metrics: Sequence[tuple[str, str, float, int]] = TABLE_METRICS) -> str:
    """Markdown: for each split and metric a table with regimes as columns (plus their
    mean) and policies as rows. Cells are ``mean`` or ``mean ± std`` over checkpoints."""
    regimes = list(summary["regimes"])
    out = io.StringIO()
    for split in summary["splits"]:
        out.write(f"## {split.capitalize()} split\n\n")
        for key, title, scale, dec in metrics:
            rows = [(label, pol["splits"][split]) for label, pol in summary["policies"].items()
                    if split in pol["splits"]]
            if not rows or not any(key in s["mean_over_regimes"] for _, s in rows):
                continue
            n_tasks = rows[0][1]["n_tasks"]
            out.write(f"### {title} — {split}, {n_tasks} tasks\n\n")
            out.write("| Policy | " + " | ".join(regimes) + " | Mean |\n")
            out.write("|---" * (len(regimes) + 2) + "|\n")
            for label, s in rows:
                cells = [_fmt(s["regimes"].get(g, {}).get(key), scale, dec) for g in regimes]
                cells.append(_fmt(s["mean_over_regimes"].get(key), scale, dec))
                out.write(f"| {label} | " + " | ".join(cells) + " |\n")
            out.write("\n")
    return out.getvalue()


def markdown_outcome_table(analyses: Sequence[Mapping[str, Any]]) -> str:
    """Markdown failure-repair table: one row per outcome class of the reference policy,
    its share, and for each other policy the share of that class it repairs (goal without
    any collision or off-road) and, in a column of its own, the share in which it harmed a
    co-player."""
    if not analyses:
        return ""
    ref = analyses[0]["reference"]
    out = io.StringIO()
    out.write(f"### Outcome analysis — reference: {ref}, {analyses[0]['n']} task-regimes\n\n")
    out.write("A repair: the ego reaches its goal without any collision or off-road event. "
              "Co-player harm (another vehicle collided or left the road) is not part of it.\n\n")
    out.write("| Reference outcome | Share (%) | " + " | ".join(
        f"{a['other']}: repaired (%) | {a['other']}: co-player harm (%)" for a in analyses) + " |\n")
    out.write("|---" * (2 + 2 * len(analyses)) + "|\n")

    def pct(a: Mapping[str, Any], name: str, key: str) -> str:
        c = a["classes"][name]
        return f"{100 * c[key]:.1f}" if c["count"] and key in c else "-"

    for name in M.OUTCOME_CLASS_NAMES:
        c0 = analyses[0]["classes"][name]
        cells = [f"{pct(a, name, 'repaired')} | {pct(a, name, 'harm')}" for a in analyses]
        out.write(f"| {name.replace('_', ' ')} | {100 * c0['share']:.1f} ({c0['count']}) | "
                  + " | ".join(cells) + " |\n")
    out.write("\n")
    return out.getvalue()


def tasks_csv(results: Sequence["EvalResult"]) -> str:
    """Every task-regime of every result as CSV rows (label, checkpoint, then :data:`TASK_COLUMNS`)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["policy", "checkpoint", *TASK_COLUMNS])
    for r in results:
        cols = [np.asarray(r.columns[c]) for c in TASK_COLUMNS]
        for i in range(cols[0].shape[0]):
            row = []
            for v in (c[i] for c in cols):
                if isinstance(v, (np.bool_, bool)):
                    row.append(int(v))
                elif isinstance(v, (np.floating, float)):
                    row.append(f"{float(v):.6g}")
                else:
                    row.append(v.item() if hasattr(v, "item") else v)
            w.writerow([r.label, r.checkpoint, *row])
    return buf.getvalue()


def summary_csv(summary: Mapping[str, Any]) -> str:
    """Long-format CSV: policy, split, regime (or ``mean``), metric, mean, std, checkpoints."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["policy", "split", "regime", "metric", "mean", "std", "checkpoints"])
    for label, pol in summary["policies"].items():
        for split, s in pol["splits"].items():
            blocks = [*s["regimes"].items(), ("mean", s["mean_over_regimes"])]
            for regime, stats in blocks:
                for metric, st in stats.items():
                    w.writerow([label, split, regime, metric, f"{st['mean']:.6g}", f"{st['std']:.6g}",
                                len(st["values"])])
    return buf.getvalue()


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _clean_nan(o: Any) -> Any:
    """Replace NaN by None so the JSON is strict (no bare NaN tokens)."""
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: _clean_nan(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean_nan(v) for v in o]
    return o


def write_results(
    out_dir: str | os.PathLike,
    results: Sequence["EvalResult"],
    reference: str | None = None,
    plots: bool = True,
    scenarios: Mapping[str, Any] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write a complete results folder atomically.

    Files: ``summary.json`` (aggregates, outcome analysis, run settings), ``summary.csv``,
    ``tasks.csv`` (every task-regime), ``tables.md``, and with ``plots`` the figures of
    :mod:`cpalgo.evaluate.plots` (``scores_<split>.png``, ``outcomes.png`` and, when two
    policies recorded trajectories and ``scenarios`` maps scenario ids to scenarios,
    ``scene.png``).

    Args:
        reference: label of the reference policy of the outcome analysis (default: the
            first label). Every other label's first checkpoint is compared with it.
        extra: run settings stored under ``"run"`` in summary.json.
    Returns: the summary dict that was written.
    """
    if not results:
        raise ValueError("results: nothing to write")
    summary = summarize_results(results)
    groups = _group_by_label(results)
    ref_label = reference if reference is not None else results[0].label
    if ref_label not in groups:
        raise ValueError(f"reference: unknown policy label {ref_label!r}; labels: {list(groups)}")
    analyses = [outcome_analysis(groups[ref_label][0], g[0]) for label, g in groups.items()
                if label != ref_label]
    summary["outcome_analysis"] = analyses
    summary["reference"] = ref_label
    summary["reference_outcome_classes"] = M.repair_table(
        groups[ref_label][0].columns["outcome_class"],
        np.zeros(len(groups[ref_label][0].columns["outcome_class"]), bool))
    if extra:
        summary["run"] = dict(extra)
    md = "# Evaluation results\n\n" + markdown_tables(summary) + markdown_outcome_table(analyses)
    with AtomicDir(out_dir) as tmp:
        write_text_atomic(tmp / "summary.json",
                          json.dumps(_clean_nan(summary), indent=2, default=_json_default) + "\n")
        write_text_atomic(tmp / "summary.csv", summary_csv(summary))
        write_text_atomic(tmp / "tasks.csv", tasks_csv(results))
        if plots:
            from cpalgo.evaluate import plots as P

            figures = P.write_standard_plots(tmp, summary, results, scenarios=scenarios)
            md += "".join(f"![{name}]({name})\n\n" for name in figures)
        write_text_atomic(tmp / "tables.md", md)
    return summary
