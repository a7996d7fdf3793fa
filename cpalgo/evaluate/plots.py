"""Evaluation figures (matplotlib, Agg canvas; never switches the user's backend).

* :func:`plot_regime_scores`: grouped bars, mean score per regime for several policies
  (error bars = std over checkpoints).
* :func:`plot_outcome_shares`: stacked bars of outcome-class shares per policy.
* :func:`plot_scene`: one scene for two policies side by side: the ego trajectory
  coloured by time, the other agents' motion, the ego's start box, its goal star and a
  marker where the ego collided (x), went off-road (triangle) or timed out (square).

Every writer saves through a temp file and ``os.replace``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np

from cpalgo.evaluate import metrics as M
from cpsim.atomic import atomic_path

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.figure import Figure

    from cpalgo.evaluate.runner import EvalResult

OUTCOME_COLORS = {
    "at_fault_collision": "#d62728",
    "offroad": "#ff7f0e",
    "completed": "#2ca02c",
    "non_at_fault_collision": "#9467bd",
    "timeout": "#7f7f7f",
}
# Simulator outcome codes (cpsim.config.Outcome), kept here so plotting needs no simulator.
_GOAL, _COLLISION, _OFFROAD, _TIMEOUT = 1, 2, 3, 4
_LANE, _ROAD_LINE, _ROAD_EDGE, _CROSSWALK = 0, 1, 2, 3


def _figure(width: float, height: float) -> "Figure":
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=110)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: "Figure", path: str | os.PathLike) -> Path:
    """Save a figure as PNG atomically (temp file in the same folder, then ``os.replace``)."""
    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    return path


def plot_regime_scores(summary: Mapping[str, Any], split: str, path: str | os.PathLike,
                       metric: str = "score") -> Path:
    """Grouped bars: for each regime (and the mean over regimes), one bar per policy."""
    regimes = list(summary["regimes"])
    labels = [lab for lab, p in summary["policies"].items() if split in p["splits"]]
    if not labels:
        raise ValueError(f"split: no policy has results for split {split!r}")
    groups = regimes + ["mean"]
    fig = _figure(max(6.0, 1.1 * len(groups) + 0.4 * len(labels)), 3.6)
    ax = fig.add_subplot(1, 1, 1)
    width = 0.8 / len(labels)
    x = np.arange(len(groups))
    for i, lab in enumerate(labels):
        s = summary["policies"][lab]["splits"][split]
        stats = [s["regimes"].get(g, {}).get(metric) for g in regimes] + [s["mean_over_regimes"].get(metric)]
        mean = np.array([np.nan if st is None else st["mean"] for st in stats])
        std = np.array([0.0 if st is None else st["std"] for st in stats])
        ax.bar(x + (i - (len(labels) - 1) / 2) * width, mean, width, yerr=std, capsize=2, label=lab)
    ax.set_xticks(x, groups, rotation=20)
    ax.set_ylabel(metric.replace("_", " ") + (" (0-100)" if metric == "score" else ""))
    if metric == "score":
        ax.set_ylim(0, 100)
    ax.set_title(f"{metric.replace('_', ' ').capitalize()} per traffic regime — {split} split")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(axis="y", alpha=0.3)
    return save_figure(fig, path)


def plot_outcome_shares(results: Sequence["EvalResult"], path: str | os.PathLike) -> Path:
    """Stacked bars: share of task-regimes in each outcome class, per policy label
    (all checkpoints of a label pooled)."""
    labels: dict[str, list[np.ndarray]] = {}
    for r in results:
        labels.setdefault(r.label, []).append(np.asarray(r.columns["outcome_class"]))
    fig = _figure(max(5.0, 1.2 * len(labels) + 2.5), 3.6)
    ax = fig.add_subplot(1, 1, 1)
    bottom = np.zeros(len(labels))
    shares = np.array([[np.mean(np.concatenate(v) == c) for c in M.OutcomeClass] for v in labels.values()])
    for j, name in enumerate(M.OUTCOME_CLASS_NAMES):
        ax.bar(np.arange(len(labels)), 100 * shares[:, j], 0.6, bottom=bottom,
               color=OUTCOME_COLORS[name], label=name.replace("_", " "))
        bottom += 100 * shares[:, j]
    ax.set_xticks(np.arange(len(labels)), list(labels), rotation=15)
    ax.set_ylabel("share of task-regimes (%)")
    ax.set_ylim(0, 100)
    ax.set_title("Outcome classes")
    ax.legend(fontsize=7, bbox_to_anchor=(1.01, 1.0), loc="upper left")
    return save_figure(fig, path)


def _draw_roads(ax: Any, scenario: Any) -> None:
    for r in range(scenario.num_roads):
        pts = scenario.road(r)
        t = int(scenario.road_types[r])
        if t == _ROAD_EDGE:
            ax.plot(pts[:, 0], pts[:, 1], color="#222222", lw=1.2, zorder=1)
        elif t == _LANE:
            ax.plot(pts[:, 0], pts[:, 1], color="#bbbbbb", lw=0.6, ls="--", zorder=1)
        elif t == _ROAD_LINE:
            ax.plot(pts[:, 0], pts[:, 1], color="#999999", lw=0.6, zorder=1)
        elif t == _CROSSWALK:
            ax.fill(pts[:, 0], pts[:, 1], color="#dddddd", zorder=0)


def _draw_episode(ax: Any, scenario: Any, traj: Mapping[str, np.ndarray], title: str) -> Any:
    """Draw one recorded episode; returns the ego's scatter (for a colour bar)."""
    from matplotlib.patches import Polygon

    xy, alive = np.asarray(traj["xy"]), np.asarray(traj["alive"], bool)  # (A, T, 2), (A, T)
    _draw_roads(ax, scenario)
    for a in range(1, xy.shape[0]):
        m = alive[a]
        if m.sum() >= 2:
            ax.plot(xy[a, m, 0], xy[a, m, 1], color="#4a78c2", lw=0.9, alpha=0.55, zorder=2)
            ax.plot(*xy[a, np.flatnonzero(m)[-1]], "o", color="#4a78c2", ms=2.5, alpha=0.7, zorder=2)
    m = alive[0]
    t = np.flatnonzero(m)
    sc = ax.scatter(xy[0, t, 0], xy[0, t, 1], c=t * 0.1, cmap="viridis", s=7, zorder=4,
                    vmin=0, vmax=xy.shape[1] * 0.1)
    heading0 = float(np.asarray(traj["heading"])[0, 0])
    size0 = np.asarray(traj["sizes"])[0]
    start = M.box_corners(xy[0, 0], heading0, size0)
    ax.add_patch(Polygon(start, closed=True, fill=False, ec="black", lw=1.2, zorder=5))
    goal = np.asarray(traj["goal_xy"])
    ax.plot(goal[0], goal[1], marker="*", color="gold", mec="black", ms=14, zorder=6)
    outcome = int(np.asarray(traj["outcome"])[0])
    last = xy[0, t[-1]] if t.size else xy[0, 0]
    marker = {_COLLISION: ("x", "red", "collision"), _OFFROAD: ("^", "orange", "off-road"),
              _TIMEOUT: ("s", "gray", "timeout")}.get(outcome)
    if marker is not None:
        ax.plot(*last, marker=marker[0], color=marker[1], ms=11, mew=2.5, zorder=7, label=marker[2])
        ax.legend(fontsize=7, loc="upper right")
    result = {_GOAL: "goal", _COLLISION: "collision", _OFFROAD: "off-road", _TIMEOUT: "timeout"}.get(outcome, "?")
    ax.set_title(f"{title}: {result}", fontsize=9)
    pts = np.concatenate([xy[alive], goal[None]], 0)
    lo, hi = pts.min(0) - 10.0, pts.max(0) + 10.0
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)
    return sc


def plot_scene(scenario: Any, traj_a: Mapping[str, np.ndarray], traj_b: Mapping[str, np.ndarray],
               titles: tuple[str, str], path: str | os.PathLike, suptitle: str = "") -> Path:
    """One scene, two policies side by side (recorded episodes from the runner).

    ``traj_*``: dicts with ``xy`` (A, T, 2) m, ``heading`` (A, T) rad, ``alive`` (A, T)
    bool, ``sizes`` (A, 2) m, ``outcome`` (A,) simulator outcome codes, ``goal_xy`` (2,)
    the ego's goal; slot 0 is the ego.
    """
    fig = _figure(11.0, 5.2)
    sc = None
    for i, (traj, title) in enumerate(zip((traj_a, traj_b), titles)):
        ax = fig.add_subplot(1, 2, i + 1)
        sc = _draw_episode(ax, scenario, traj, title)
    if sc is not None:
        fig.colorbar(sc, ax=fig.axes, shrink=0.8, label="time (s)")
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    return save_figure(fig, path)


def pick_contrast_task(a: "EvalResult", b: "EvalResult") -> int | None:
    """Row index of a recorded task-regime where ``a`` fails and ``b`` completes cleanly
    (else any row recorded by both where their outcome classes differ, else any common
    recorded row); None when the two share no recorded row."""
    common = sorted(set(a.trajectories) & set(b.trajectories))
    if not common:
        return None
    ca, cb = np.asarray(a.columns["outcome_class"]), np.asarray(b.columns["outcome_class"])
    done = int(M.OutcomeClass.COMPLETED)
    for rows in ([i for i in common if ca[i] != done and cb[i] == done],
                 [i for i in common if ca[i] != cb[i]], common):
        if rows:
            return rows[0]
    return None


def write_standard_plots(out: str | os.PathLike, summary: Mapping[str, Any],
                         results: Sequence["EvalResult"],
                         scenarios: Mapping[str, Any] | None = None) -> list[str]:
    """Write the standard figures into folder ``out``; returns their file names."""
    out = Path(out)
    names = []
    for split in summary["splits"]:
        name = f"scores_{split}.png"
        plot_regime_scores(summary, split, out / name)
        names.append(name)
    plot_outcome_shares(results, out / "outcomes.png")
    names.append("outcomes.png")
    labels: dict[str, EvalResult] = {}
    for r in results:
        labels.setdefault(r.label, r)
    firsts = list(labels.values())
    if scenarios and len(firsts) >= 2:
        row = pick_contrast_task(firsts[0], firsts[1])
        if row is not None:
            sid = str(firsts[0].columns["scenario_id"][row])
            if sid in scenarios:
                regime = firsts[0].columns["regime"][row]
                plot_scene(scenarios[sid], firsts[0].trajectories[row], firsts[1].trajectories[row],
                           (firsts[0].label, firsts[1].label), out / "scene.png",
                           suptitle=f"{sid} — {regime} traffic")
                names.append("scene.png")
    return names
