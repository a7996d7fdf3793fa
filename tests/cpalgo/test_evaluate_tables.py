"""Tables, JSON/CSV and plots from synthetic evaluation results (no simulator)."""

from __future__ import annotations

import csv
import io
import json

import numpy as np
import pytest

from cpalgo.evaluate import metrics as M
from cpalgo.evaluate import tables as TB
from cpalgo.evaluate.runner import EvalResult

REGIMES = ["idm", "replay", "normal"]


def _result(label: str, goal_rate: float, seed: int, n_tasks: int = 6, record: bool = False) -> EvalResult:
    rng = np.random.default_rng(seed)
    rows = [(s, r, t) for s in ("interactive", "random") for r in REGIMES for t in range(n_tasks)]
    n = len(rows)
    goal = rng.random(n) < goal_rate
    fault = ~goal & (rng.random(n) < 0.5)
    off = ~goal & ~fault & (rng.random(n) < 0.5)
    comfort, align, center = rng.random(n), rng.random(n), rng.random(n)
    cols = {
        "split": np.array([s for s, _, _ in rows]), "regime": np.array([r for _, r, _ in rows]),
        "task": np.array([t for _, _, t in rows]), "scenario_id": np.array([f"sc{t}" for _, _, t in rows]),
        "ego": np.zeros(n, np.int64), "goal": goal, "at_fault_collision": fault,
        "non_at_fault_collision": np.zeros(n, bool), "offroad": off,
        "timeout": ~goal & ~fault & ~off, "comfort": comfort, "lane_align": align, "lane_center": center,
        "score": M.task_score(goal, fault, off, comfort, align, center),
        "co_player_harm": rng.integers(0, 2, n), "steps_alive": np.full(n, 50), "goal_step": np.full(n, 40),
        "outcome_class": M.outcome_class(goal, fault, np.zeros(n, bool), off),
    }
    traj = {}
    if record:
        T, A = 12, 3
        for row in range(4):
            xy = np.cumsum(np.ones((A, T, 2)), axis=1) + np.arange(A)[:, None, None] * 4.0
            traj[row] = {"xy": xy, "heading": np.full((A, T), np.pi / 4), "alive": np.ones((A, T), bool),
                         "sizes": np.tile([4.5, 2.0], (A, 1)), "goal_xy": xy[0, -1] + 1.0,
                         "outcome": np.array([2 if label == "anchor" else 1, 1, 1])}
    return EvalResult(label, f"{label}-{seed}.zip", cols, traj)


def test_summary_mean_and_std_over_checkpoints():
    a1, a2 = _result("anchor", 0.5, 1), _result("anchor", 0.5, 2)
    s = TB.summarize_results([a1, a2])
    st = s["policies"]["anchor"]["splits"]["random"]["regimes"]["normal"]["score"]
    m = (a1.columns["split"] == "random") & (a1.columns["regime"] == "normal")
    per = [a1.columns["score"][m].mean(), a2.columns["score"][m].mean()]
    assert st["mean"] == pytest.approx(np.mean(per))
    assert st["std"] == pytest.approx(np.std(per, ddof=1))
    over = s["policies"]["anchor"]["splits"]["random"]["mean_over_regimes"]["completion"]
    want = [np.mean([r.columns["goal"][(r.columns["split"] == "random") & (r.columns["regime"] == g)].mean()
                     for g in REGIMES]) for r in (a1, a2)]
    assert over["values"] == pytest.approx(want)
    assert s["regimes"] == REGIMES and s["splits"] == ["interactive", "random"]


def test_markdown_layout_regimes_as_columns_policies_as_rows():
    md = TB.markdown_tables(TB.summarize_results([_result("anchor", 0.5, 1), _result("counterplay", 0.9, 3)]))
    assert "## Interactive split" in md and "## Random split" in md
    header = "| Policy | idm | replay | normal | Mean |"
    assert md.count(header) == 2 * len(TB.TABLE_METRICS)
    lines = [ln for ln in md.splitlines() if ln.startswith("| counterplay |")]
    assert len(lines) == 2 * len(TB.TABLE_METRICS)
    assert all(ln.count("|") == len(REGIMES) + 3 for ln in lines)


def test_outcome_analysis_counts_repairs():
    ref, other = _result("anchor", 0.3, 1), _result("counterplay", 0.9, 5)
    # some of the other policy's goals come with a not-at-fault collision: not repairs
    other.columns["non_at_fault_collision"] = other.columns["goal"] & (np.arange(other.num_rows) % 4 == 0)
    a = TB.outcome_analysis(ref, other)
    cls = ref.columns["outcome_class"]
    # a repair: goal without any collision or off-road; co-player harm does not matter
    repaired = other.columns["goal"] & ~other.columns["non_at_fault_collision"]
    harm = other.columns["co_player_harm"] > 0
    assert (repaired & harm).any()
    t = a["classes"]["timeout"]
    m = cls == M.OutcomeClass.TIMEOUT
    assert t["count"] == int(m.sum())
    assert t["repaired"] == pytest.approx(repaired[m].mean())
    assert t["harm"] == pytest.approx(harm[m].mean())
    md = TB.markdown_outcome_table([a])
    assert "counterplay: repaired (%) | counterplay: co-player harm (%)" in md
    line = next(ln for ln in md.splitlines() if ln.startswith("| timeout |"))
    assert line.split("|")[3].strip() == f"{100 * repaired[m].mean():.1f}"
    assert line.split("|")[4].strip() == f"{100 * harm[m].mean():.1f}"
    other.columns["regime"] = other.columns["regime"][::-1].copy()
    with pytest.raises(ValueError, match="regime"):
        TB.outcome_analysis(ref, other)


def test_write_results_folder_complete(tmp_path):
    results = [_result("anchor", 0.4, 1, record=True), _result("anchor", 0.4, 2),
               _result("counterplay", 0.8, 3, record=True)]
    scen = _scenario()
    out = tmp_path / "res"
    TB.write_results(out, results, scenarios={f"sc{t}": scen for t in range(6)}, extra={"n": 6})
    names = sorted(p.name for p in out.iterdir())
    assert names == ["outcomes.png", "scene.png", "scores_interactive.png", "scores_random.png",
                     "summary.csv", "summary.json", "tables.md", "tasks.csv"]
    js = json.loads((out / "summary.json").read_text())
    assert js["run"] == {"n": 6} and js["reference"] == "anchor"
    assert js["outcome_analysis"][0]["other"] == "counterplay"
    rows = list(csv.DictReader(io.StringIO((out / "tasks.csv").read_text())))
    assert len(rows) == 3 * results[0].num_rows
    assert rows[0]["policy"] == "anchor" and rows[0]["goal"] in ("0", "1")
    assert (out / "scores_random.png").read_bytes()[:4] == b"\x89PNG"
    assert "![scene.png](scene.png)" in (out / "tables.md").read_text()
    # no temp folders left behind next to the result
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]


def test_interrupted_write_leaves_previous_results(tmp_path, monkeypatch):
    out = tmp_path / "res"
    TB.write_results(out, [_result("anchor", 0.5, 1)], plots=False)
    before = (out / "summary.json").read_text()

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(TB, "tasks_csv", boom)
    with pytest.raises(KeyboardInterrupt):
        TB.write_results(out, [_result("anchor", 0.9, 7)], plots=False)
    assert (out / "summary.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]
    fresh = tmp_path / "fresh"
    with pytest.raises(KeyboardInterrupt):
        TB.write_results(fresh, [_result("anchor", 0.9, 7)], plots=False)
    assert not fresh.exists()


def test_write_results_rejects_unknown_reference(tmp_path):
    with pytest.raises(ValueError, match="reference"):
        TB.write_results(tmp_path / "r", [_result("anchor", 0.5, 1)], reference="nope", plots=False)
    assert not (tmp_path / "r").exists()


def _scenario():
    import cpsim

    T = 91
    xy = np.zeros((3, T, 2), np.float32)
    xy[:, :, 0] = np.linspace(0, 12, T)[None]
    xy[:, :, 1] = np.array([0.0, 4.0, 8.0])[:, None]
    pts = np.array([[-5, -2], [30, -2], [-5, 0], [30, 0]], np.float32)
    return cpsim.Scenario(
        id="sc", log_xy=xy, log_heading=np.zeros((3, T)), log_velocity=np.zeros((3, T, 2)),
        log_valid=np.ones((3, T), bool), goal_xy=xy[:, -1], sizes=np.tile([4.5, 2.0], (3, 1)),
        agent_types=np.zeros(3), road_points=pts, road_offsets=np.array([0, 2, 4]),
        road_types=np.array([2, 0]), ego_index=0)


def test_results_have_ordinary_permissions(tmp_path):
    import os
    import stat

    out = tmp_path / "res"
    TB.write_results(out, [_result("anchor", 0.5, 1)], plots=True)
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o777 & ~mask
    for p in out.iterdir():
        assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~mask, p.name
