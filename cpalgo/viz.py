"""Pictures of CounterPlay searches (:class:`~cpalgo.counterplay.records.SearchRecord`).

* :func:`plot_search`: one search as a figure in the style of the seed paper's Fig. 1 and
  its qualitative figure: the map; the factual branch from the root to its end, with the
  failure marked (cross: collision, triangle: off-road, circle: timeout); the root (open
  box at the focal pose, diamond); each panel style's path from the root in its own
  colour (cautious blue to aggressive red) with the style names in the legend; the
  verification reruns dashed; the chosen (and verified) branch drawn wide; the goal as a
  star; co-players as grey arrows along their factual paths; dots every second along the
  focal paths (dense dots: slow); and a panel with the focal critic value trace, the roots
  of the window, ``V_max``, ``V_f`` and the threshold ``V_thr``.
* :func:`animate_search`: a GIF (or MP4) of the factual branch and the chosen retry side
  by side (the best-ranked candidate when no teacher was chosen).
* :func:`render_search`: either, by the output file's extension.
* :func:`write_search_files`: a run's kept searches beside its checkpoint and the figure
  of its latest verified search (what the main job writes).

Figures use matplotlib's Agg canvas directly (a user's pyplot backend is never touched);
files are written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from cpalgo.counterplay.records import BranchTrace, SearchRecord
from cpsim.atomic import atomic_path
from cpsim.render import plot_roads, write_video

__all__ = ["STYLE_COLORS", "OUTCOME_MARKERS", "plot_search", "animate_search", "render_search", "branch_color",
           "write_search_files"]

#: Panel style -> colour (cautious -> aggressive: blue -> red); the factual branch is black.
STYLE_COLORS: dict[str, str] = {
    "cautious": "#2166ac",
    "cautious-normal": "#35a3c2",
    "normal": "#33a02c",
    "normal-aggressive": "#f28e1c",
    "aggressive": "#d7191c",
    "factual": "#111111",
}
_FALLBACK = ("#6a3d9a", "#b15928", "#e7298a", "#666666", "#1b9e77", "#7570b3")
#: Focal outcome -> (marker, size); goals are not marked (the star is the goal).
OUTCOME_MARKERS: dict[str, tuple[str, float]] = {"collision": ("X", 130.0), "offroad": ("^", 110.0),
                                                 "timeout": ("o", 90.0)}
FOCAL_COLOR = "#7b2fbe"
COPLAYER_COLOR = "#8c8c8c"
DECISIONS_PER_SECOND = 10


def branch_color(name: str, panel: Sequence[str] = ()) -> str:
    """Colour of a branch (``verify:<style>`` takes the style's colour)."""
    base = name.split(":", 1)[1] if name.startswith("verify:") else name
    if base in STYLE_COLORS:
        return STYLE_COLORS[base]
    idx = list(panel).index(base) if base in panel else abs(hash(base))
    return _FALLBACK[idx % len(_FALLBACK)]


def _new_figure(size: tuple[float, float], dpi: int) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def _box(xy: np.ndarray, heading: float, size: np.ndarray) -> np.ndarray:
    length, width = float(size[0]), float(size[1])
    c, s = np.cos(heading), np.sin(heading)
    corners = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]]) * [length, width]
    return corners @ np.array([[c, s], [-s, c]]) + xy


def _focal_path(b: BranchTrace, focal: int) -> np.ndarray:
    end = b.focal_end(focal)
    return b.xy[: end + 1, focal]


def _extent(record: SearchRecord, margin: float = 10.0, min_span: float = 40.0) -> tuple[float, float, float, float]:
    """The focal paths of every branch and the goal, with a margin."""
    pts = [b.xy[b.valid[:, record.focal], record.focal] for b in record.branches]
    pts.append(record.goal[record.focal][None])
    p = np.concatenate([x for x in pts if x.size])
    lo, hi = p.min(axis=0) - margin, p.max(axis=0) + margin
    centre, span = (lo + hi) / 2, np.maximum(hi - lo, min_span)
    rp = record.road_points
    if rp.size:  # never zoom out beyond the map itself
        span = np.minimum(span, rp.max(axis=0) - rp.min(axis=0) + 2 * margin)
        span = np.maximum(span, min_span)
    return centre[0] - span[0] / 2, centre[0] + span[0] / 2, centre[1] - span[1] / 2, centre[1] + span[1] / 2


def _set_view(ax: Any, extent: tuple[float, float, float, float]) -> None:
    """Limits of ``extent`` widened to the axes' own shape, at equal scale in x and y."""
    x0, x1, y0, y1 = extent
    bbox = ax.get_position()
    w_in, h_in = ax.figure.get_size_inches()
    shape = (bbox.width * w_in) / (bbox.height * h_in)
    w, h = x1 - x0, y1 - y0
    if w / h < shape:
        x0, x1 = (x0 + x1) / 2 - h * shape / 2, (x0 + x1) / 2 + h * shape / 2
    else:
        y0, y1 = (y0 + y1) / 2 - w / shape / 2, (y0 + y1) / 2 + w / shape / 2
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal", adjustable="box")


def _branch_label(record: SearchRecord, b: BranchTrace) -> str:
    if b.kind == "factual":
        text = f"factual (w0): {b.outcome}"
        if b.outcome == "goal":
            text += f" @{b.arrival_step}"
    elif b.kind == "candidate":
        text = f"{b.name}: {b.outcome}"
        if b.outcome == "goal":
            text += f" @{b.arrival_step}"
        if b.admissible:
            text += ", admissible"
        if record.chosen is not None and b is record.chosen_branch:
            text += {"verified": " - CHOSEN, verified", "discarded": " - CHOSEN, failed verification",
                     "unverified": " - CHOSEN (no verification)"}[record.status]
    else:
        text = f"rerun {b.name.split(':', 1)[1]}: {b.outcome}"
    harmed = b.harmed(record.focal)
    if harmed:
        text += f", harms {len(harmed)}"
    return text


def plot_search(record: SearchRecord, fig: Any = None, *, size: tuple[float, float] = (12.0, 7.6),
                dpi: int = 110) -> Any:
    """Draw one search (see the module docstring); returns the matplotlib Figure.

    Every branch of the record is one ``Line2D`` of the map axes with ``gid``
    ``"branch:<name>"`` (factual, one per panel style, the verification reruns).
    """
    from matplotlib import patheffects as pe
    from matplotlib.lines import Line2D
    from matplotlib.patches import Polygon

    if fig is None:
        fig = _new_figure(size, dpi)
    ax = fig.add_axes([0.04, 0.07, 0.56, 0.83])
    plot_roads(ax, record.road_points, record.road_offsets, record.road_types)
    _set_view(ax, _extent(record))
    ax.tick_params(labelsize=7)
    focal = record.focal
    f = record.factual

    # co-players: boxes at the root, grey arrows along their factual paths
    others = np.flatnonzero(f.valid[0])
    for a in others.tolist():
        if a == focal:
            continue
        ax.add_patch(Polygon(_box(f.xy[0, a], f.heading[0, a], record.size[a]), closed=True, fc="#d0d0d0",
                             ec=COPLAYER_COLOR, lw=0.7, zorder=5))
        path = f.xy[f.valid[:, a], a]
        if path.shape[0] > 1 and np.linalg.norm(path[-1] - path[0]) > 1.0:
            ax.plot(path[:, 0], path[:, 1], color=COPLAYER_COLOR, lw=1.0, alpha=0.8, zorder=6)
            tail = path[max(0, path.shape[0] - 4)]
            ax.annotate("", xy=path[-1], xytext=tail, zorder=6,
                        arrowprops=dict(arrowstyle="-|>", color=COPLAYER_COLOR, lw=1.0, mutation_scale=12))

    # branches: verification reruns (dashed, below), candidates, factual on top; chosen widest
    chosen = record.chosen_branch
    order = sorted(record.branches, key=lambda b: {"verify-factual": 0, "verify-candidate": 1, "candidate": 2,
                                                   "factual": 4}[b.kind] + (1 if b is chosen else 0))
    handles = []
    for b in order:
        color = branch_color(b.name, record.panel)
        path = _focal_path(b, focal)
        lw, ls, alpha, z = 1.6, "-", 0.95, 8
        effects = None
        if b.kind.startswith("verify"):
            lw, ls, alpha, z = 1.2, (0, (4, 2.5)), 0.9, 7
        elif b is chosen:  # a wide band under the other paths, so that none is hidden
            lw, alpha, z = 5.5, 0.75, 6.5
            effects = [pe.Stroke(linewidth=8.0, foreground="white", alpha=0.9), pe.Normal()]
        elif b.kind == "factual":
            lw, z = 2.2, 9
        (line,) = ax.plot(path[:, 0], path[:, 1], color=color, lw=lw, ls=ls, alpha=alpha, zorder=z,
                          solid_capstyle="round", gid=f"branch:{b.name}", label=_branch_label(record, b))
        if effects:
            line.set_path_effects(effects)
        if not b.kind.startswith("verify"):
            ticks = path[DECISIONS_PER_SECOND::DECISIONS_PER_SECOND]
            if ticks.size:
                ax.scatter(ticks[:, 0], ticks[:, 1], s=9, color=color, zorder=z, edgecolors="white",
                           linewidths=0.4)
        marker = OUTCOME_MARKERS.get(b.outcome)
        if marker is not None and not b.kind.startswith("verify"):
            end = path[-1]
            mcolor = "#e31a1c" if (b.kind == "factual" and b.outcome == "collision") else color
            ax.scatter([end[0]], [end[1]], marker=marker[0], s=marker[1] * (1.25 if b.kind == "factual" else 0.8),
                       c=mcolor, edgecolors="black" if b.kind == "factual" else "white", linewidths=1.0,
                       zorder=12)
        for a in b.harmed(focal):  # other vehicles this branch harmed: small crosses
            stop = [s for s in (b.first_collision_step[a], b.first_offroad_step[a]) if s >= 0]
            t = int(np.clip(min(stop) - record.root_step + 1, 0, b.length))
            ax.scatter([b.xy[t, a, 0]], [b.xy[t, a, 1]], marker="x", s=40, c=color, linewidths=1.6, zorder=11)
        handles.append((b, line))

    # the focal vehicle at the root (open box), the root marker and the goal
    ax.add_patch(Polygon(_box(f.xy[0, focal], f.heading[0, focal], record.size[focal]), closed=True, fill=False,
                         ec=FOCAL_COLOR, lw=1.8, zorder=13))
    ax.scatter([f.xy[0, focal, 0]], [f.xy[0, focal, 1]], marker="D", s=42, c="white", edgecolors="black",
               linewidths=1.2, zorder=14)
    ax.annotate(f"root t={record.root_step}", f.xy[0, focal], xytext=(6, 6), textcoords="offset points",
                fontsize=8, zorder=15, path_effects=[pe.withStroke(linewidth=2.5, foreground="white")])
    goal = record.goal[focal]
    ax.scatter([goal[0]], [goal[1]], marker="*", s=320, c="#ffd700", edgecolors="black", linewidths=1.0, zorder=14)
    if np.isfinite(record.goal_radius) and record.goal_radius > 0:
        from matplotlib.patches import Circle

        ax.add_patch(Circle(goal, record.goal_radius, fill=False, ec="#b8860b", ls=(0, (3, 2)), lw=1.0, zorder=4))

    # legend: branches in panel order, then the symbols
    rank = {"factual": 0, "candidate": 1, "verify-factual": 2, "verify-candidate": 3}
    # by identity: single-style panels repeat a branch name, and == on traces compares arrays
    order = {id(b): i for i, b in enumerate(record.branches)}
    handles.sort(key=lambda h: (rank[h[0].kind], order[id(h[0])]))
    symbols = [
        Line2D([], [], ls="", marker="D", mfc="white", mec="black", label="root (restored state)"),
        Line2D([], [], ls="", marker="*", ms=13, mfc="#ffd700", mec="black", label="goal (dashed: goal radius)" if np.isfinite(record.goal_radius) else "goal"),
        Line2D([], [], ls="", marker="X", ms=9, mfc="#e31a1c", mec="black", label="collision"),
        Line2D([], [], ls="", marker="^", ms=8, mfc="#999999", mec="black", label="off-road"),
        Line2D([], [], ls="", marker="o", ms=8, mfc="#999999", mec="black", label="timeout"),
        Line2D([], [], color=COPLAYER_COLOR, marker=">", ms=5, label="co-players (factual)"),
        Line2D([], [], ls="", marker=".", color="#444444", label="1 s ticks"),
    ]
    artists = [h[1] for h in handles] + symbols
    fig.legend(artists, [a.get_label() for a in artists],
               loc="upper left", bbox_to_anchor=(0.615, 0.905), fontsize=7.5, frameon=False, handlelength=2.6)

    # title
    fig.suptitle(f"{record.scenario_id} ({record.family}): focal slot {focal} failed by {record.failure} at decision "
                 f"{record.failure_step}; backtracked to root {record.root_step} (depth {record.depth})\n"
                 f"teacher: {record.teacher or 'none admissible'} ({record.status}); searched in generation {record.generation}",
                 fontsize=10, x=0.04, ha="left", y=0.985)

    _plot_values(fig.add_axes([0.675, 0.08, 0.3, 0.34]), record)
    return fig


def _plot_values(ax: Any, record: SearchRecord) -> None:
    """The focal critic value trace with the backtracking quantities."""
    v = record.values
    t = np.arange(v.size)
    ax.plot(t, v, color="#444444", lw=1.2, zorder=2)
    roots = record.root_steps[record.root_steps < v.size]
    ax.scatter(roots, v[roots], s=16, facecolors="white", edgecolors="#444444", zorder=3, label="roots in window")
    ax.scatter([record.root_step], [v[record.root_step]], marker="D", s=36, c="white", edgecolors="black",
               linewidths=1.2, zorder=4, label=f"root t={record.root_step}")
    marker = OUTCOME_MARKERS.get(record.failure, ("o", 60))[0]
    ax.scatter([record.failure_step], [v[record.failure_step]], marker=marker, s=50, c="#e31a1c",
               edgecolors="black", zorder=4, label=f"{record.failure} t={record.failure_step}")
    for value, name, color, ls in ((record.v_max, "V_max", "#1f78b4", "--"), (record.v_fail, "V_f", "#e31a1c", "--"),
                                   (record.threshold, f"V_thr (rho={record.rho:g})", "#33a02c", "-")):
        if np.isfinite(value):
            ax.axhline(value, color=color, ls=ls, lw=1.0, zorder=1, label=name)
    lo, hi = record.failure_step - record.window[1], record.failure_step - record.window[0]
    if record.backtrack == "value":
        ax.axvspan(max(lo, 0), hi, color="#cccccc", alpha=0.35, zorder=0, lw=0)
    ax.set_xlim(-1, max(record.failure_step + 2, 10))
    ax.set_xlabel("decision (0.1 s)", fontsize=7)
    ax.set_ylabel("focal critic value", fontsize=7)
    title = "backtracking: focal value trace (grey: window)"
    if record.backtrack == "value" and np.isfinite(record.threshold):
        above = [r for r in roots if v[r] >= record.threshold]
        title += "\nroot: latest root with V >= V_thr" if above else \
            "\nno root reaches V_thr: the window's earliest root"
    elif record.backtrack != "value":
        title += "\nfixed-depth backtracking"
    ax.set_title(title, fontsize=8)
    ax.tick_params(labelsize=6.5)
    ax.legend(fontsize=6, loc="best", frameon=True, framealpha=0.85, ncol=2)


# ---------------------------------------------------------------------------- animation
def _retry(record: SearchRecord) -> tuple[BranchTrace, str]:
    chosen = record.chosen_branch
    if chosen is not None:
        return chosen, f"{chosen.name} (chosen, {record.status})"
    best = max(record.candidates, key=lambda b: b.rank_key)
    return best, f"{best.name} (best-ranked, not admissible)"


def animate_search(record: SearchRecord, path: str | os.PathLike | None = None, *, fps: float = 10.0,
                   hold_s: float = 1.5, size: tuple[float, float] = (10.0, 5.4), dpi: int = 80) -> list[np.ndarray]:
    """Frames of the factual branch (left) and the chosen retry (right) side by side, from
    the root to the end of the longer one; written to ``path`` (.gif / .mp4) when given.
    Returns the frames ((H, W, 3) uint8)."""
    from matplotlib import patheffects as pe
    from matplotlib.patches import Polygon

    retry, retry_title = _retry(record)
    panels = [(record.factual, "factual (w0)"), (retry, retry_title)]
    fig = _new_figure(size, dpi)
    focal = record.focal
    extent = _extent(record)
    state = []
    for k, (b, title) in enumerate(panels):
        ax = fig.add_axes([0.01 + 0.5 * k, 0.02, 0.48, 0.86])
        plot_roads(ax, record.road_points, record.road_offsets, record.road_types)
        _set_view(ax, extent)
        ax.set_xticks([])
        ax.set_yticks([])
        goal = record.goal[focal]
        ax.scatter([goal[0]], [goal[1]], marker="*", s=260, c="#ffd700", edgecolors="black", zorder=9)
        color = branch_color(b.name, record.panel)
        (trail,) = ax.plot([], [], color=color, lw=2.5, zorder=7, solid_capstyle="round", animated=True)
        boxes = []
        for a in range(b.xy.shape[1]):
            fc = FOCAL_COLOR if a == focal else "#bdbdbd"
            poly = Polygon(_box(b.xy[0, a], b.heading[0, a], record.size[a]), closed=True, fc=fc,
                           ec="black", lw=0.7, zorder=10 if a == focal else 8, visible=bool(b.valid[0, a]),
                           animated=True)
            ax.add_patch(poly)
            boxes.append(poly)
        ax.set_title(title, fontsize=10, color=color if b.kind != "factual" else "black")
        note = ax.text(0.02, 0.02, "", transform=ax.transAxes, fontsize=9, zorder=20, animated=True,
                       path_effects=[pe.withStroke(linewidth=3, foreground="white")])
        marker, msize = OUTCOME_MARKERS.get(b.outcome, ("o", 0.0))
        end_xy = b.xy[b.focal_end(focal), focal]
        ending = ax.scatter([end_xy[0]], [end_xy[1]], marker=marker, s=msize * 1.2, zorder=12, edgecolors="black",
                            c="#e31a1c" if b.outcome == "collision" else color, visible=False, animated=True)
        state.append((b, trail, boxes, note, ending))
    fig.suptitle(f"{record.scenario_id}: retry from root t={record.root_step} (factual failure: {record.failure} at "
                 f"t={record.failure_step})", fontsize=10)

    # static layers (map, goal, titles) are drawn once; each frame redraws the moving artists only
    canvas = fig.canvas
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)
    n = max(b.length for b, *_ in state) + 1
    frames = []
    for t in range(n):
        for b, trail, boxes, note, ending in state:
            tt = min(t, b.length)
            end = b.focal_end(focal)
            p = b.xy[: min(tt, end) + 1, focal]
            trail.set_data(p[:, 0], p[:, 1])
            for a, poly in enumerate(boxes):
                alive = bool(b.valid[tt, a])
                last = np.flatnonzero(b.valid[: tt + 1, a])
                if not alive and last.size and a == focal:  # keep the focal car where it ended
                    i = int(last[-1])
                    poly.set_xy(_box(b.xy[i, a], b.heading[i, a], record.size[a]))
                    poly.set_visible(True)
                    poly.set_alpha(0.45)
                    continue
                poly.set_visible(alive)
                if alive:
                    poly.set_xy(_box(b.xy[tt, a], b.heading[tt, a], record.size[a]))
            msg = f"t = {record.root_step + tt} ({tt / DECISIONS_PER_SECOND:.1f} s after the root)"
            if tt >= end:
                msg += f" - {b.outcome}"
                ending.set_visible(b.outcome in OUTCOME_MARKERS)
            note.set_text(msg)
        canvas.restore_region(background)
        for _, trail, boxes, note, ending in state:
            for artist in sorted([trail, *boxes, ending, note], key=lambda x: x.get_zorder()):
                artist.axes.draw_artist(artist)
        frames.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
    frames += [frames[-1]] * int(round(hold_s * fps))
    if path is not None:
        write_video(frames, path, fps=fps)
    return frames


def render_search(record: SearchRecord, path: str | os.PathLike) -> Path:
    """Write :func:`plot_search` (``.png``, ``.pdf``, ``.svg``) or :func:`animate_search`
    (``.gif``, ``.mp4``) of ``record`` to ``path``, atomically. Returns the path."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext in (".gif", ".mp4"):
        animate_search(record, path)
        return path
    if ext not in (".png", ".pdf", ".svg"):
        raise ValueError(f"path: unsupported extension {ext!r}; accepted: .png .pdf .svg .gif .mp4")
    fig = plot_search(record)
    with atomic_path(path, suffix=ext) as tmp:
        fig.savefig(tmp, format=ext[1:])
    return path


def write_search_files(model: Any, checkpoint: str | os.PathLike, figure: str = "search.png") -> dict[str, str]:
    """Save ``model``'s kept searches beside ``checkpoint`` (``<name>.searches.npz``) and
    draw the latest verified one to ``figure`` in the checkpoint's folder (skipped, with a
    note, when matplotlib is not installed). Returns ``{"searches": ..., "figure": ...}``
    for what was written. A counterfactual run that kept no search still gets its (empty)
    search file, so ``counterplay searches`` can say so; other models get nothing (``{}``)."""
    from cpalgo.counterplay.records import save_records, search_records

    records = search_records(model)
    if not len(records) and not (getattr(model, "counterfactual", False) and getattr(model, "keep_searches", 0)):
        return {}
    checkpoint = Path(checkpoint)
    files = {"searches": str(save_records(records, checkpoint))}
    verified = records.latest("verified")
    if verified is not None:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            print("search figure skipped: matplotlib is not installed (pip install 'counterplay[plot]')")
        else:
            files["figure"] = str(render_search(verified, checkpoint.parent / figure))
    return files
