"""Kept searches: records, save / load, the figure and the GIF, the `searches` command,
and keep_searches=0."""

from __future__ import annotations

import dataclasses
import gc

import numpy as np
import pytest
import torch as th

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")
pytest.importorskip("matplotlib", reason="figures need matplotlib")

import cpalgo.counterplay.driver as driver_module  # noqa: E402
import cpalgo.counterplay.records as records_module  # noqa: E402
from cpalgo import CounterPlay, cli  # noqa: E402
from cpalgo.counterplay.branches import BranchResult  # noqa: E402
from cpalgo.counterplay.records import (  # noqa: E402
    SearchRecord,
    SearchRecords,
    failure_anatomy,
    format_anatomy,
    format_table,
    load_records,
    save_records,
    search_records,
    searches_path,
)
from cpalgo.viz import animate_search, plot_search, render_search, write_search_files  # noqa: E402
from cpsim import SelfPlayVecEnv  # noqa: E402

EPISODE = 40
POLICY = dict(lstm_hidden_size=16, net_arch=[32])


pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def make_env() -> SelfPlayVecEnv:
    return SelfPlayVecEnv(num_worlds=2, max_agents=4, num_scenarios=4, seed=1, episode_steps=EPISODE,
                          num_partners=4, num_road=16)


def make_model(env: SelfPlayVecEnv | None = None, **kw) -> CounterPlay:
    env = env if env is not None else make_env()
    args = dict(n_steps=EPISODE, batch_size=64, n_epochs=1, seed=0, policy_kwargs=POLICY, branch_cap=3.0)
    args.update(kw)
    return CounterPlay("MlpLstmPolicy", env, **args)


def force_teachers(mp: pytest.MonkeyPatch) -> None:
    """A random policy rarely completes a task: pick the last candidate as the teacher and
    let verification pass every other time, so that verified and discarded searches exist."""
    calls = {"n": 0}

    def verify(factual, candidate):
        calls["n"] += 1
        return calls["n"] % 2 == 1

    mp.setattr(driver_module, "choose_teacher", lambda factual, candidates, selection: len(candidates) - 1)
    mp.setattr(driver_module, "verify", verify)


def run_generations(model: CounterPlay, n: int = 3) -> CounterPlay:
    """``n`` generations (a generation's searches run during the next one)."""
    model.learn(1)
    for _ in range(n - 1):
        model.learn(1, reset_num_timesteps=False)
    return model


@pytest.fixture(scope="module")
def kept():
    """A short learn that keeps every search: (model, records)."""
    with pytest.MonkeyPatch.context() as mp:
        force_teachers(mp)
        th.set_num_threads(1)
        model = run_generations(make_model(keep_searches=8))
    records = list(search_records(model))
    assert records, "no search ran"
    statuses = {r.status for r in records}
    assert {"verified", "discarded"} <= statuses, statuses
    return model, records


def _by_status(records, status: str) -> SearchRecord:
    return next(r for r in records if r.status == status)


def _assert_same(a, b, where: str = "") -> None:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=where)
    elif isinstance(a, float) and np.isnan(a):
        assert isinstance(b, float) and np.isnan(b), where
    elif isinstance(a, (list, tuple)) and a and dataclasses.is_dataclass(a[0]):
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{where}[{k}]")
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            _assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    else:
        assert tuple(a) == tuple(b) if isinstance(a, (list, tuple)) else a == b, (where, a, b)


# ---------------------------------------------------------------------------- records
def test_a_record_holds_the_search(kept):
    model, records = kept
    r = _by_status(records, "verified")
    assert r.panel == model.panel
    assert [b.kind for b in r.branches] == ["factual"] + ["candidate"] * len(model.panel) + \
        ["verify-factual", "verify-candidate"]
    assert [b.name for b in r.candidates] == list(model.panel)
    assert r.teacher == model.panel[-1] and r.verified is True
    assert r.failure in ("collision", "offroad", "timeout") and 0 <= r.root_step < r.failure_step < r.deadline
    assert r.depth == r.failure_step - r.root_step and model.window[0] <= r.depth <= model.window[1]
    # the value trace and the threshold select_root used: the kept root is the latest one above it
    assert r.values.shape == (r.failure_step + 1,)
    assert r.v_max >= r.threshold >= r.v_fail or r.v_max <= r.threshold <= r.v_fail
    above = [t for t in r.root_steps if r.values[t] >= r.threshold]
    assert r.root_step == (max(above) if above else min(r.root_steps))
    a = r.factual.xy.shape[1]
    for b in r.branches:
        assert b.xy.shape == (b.length + 1, a, 2) and b.heading.shape == b.valid.shape == (b.length + 1, a)
        assert np.isfinite(b.xy).all() and np.isfinite(b.heading).all()
        assert b.valid[0, r.focal] and r.root_step + b.length <= r.deadline
        assert b.outcome in ("goal", "collision", "offroad", "timeout") and len(b.rank_key) == 3
        # every branch starts from the same root
        np.testing.assert_array_equal(b.xy[0], r.factual.xy[0])
    assert all(isinstance(b.admissible, bool) for b in r.candidates)
    assert r.road_points.ndim == 2 and r.road_offsets[-1] == r.road_points.shape[0]
    # a discarded search keeps its reruns too; a search without a teacher has none
    d = _by_status(records, "discarded")
    assert d.verified is False and len(d.verification) == 2


def test_records_hold_no_tensors(kept):
    _, records = kept

    def walk(x, where):
        assert not isinstance(x, th.Tensor), where
        if dataclasses.is_dataclass(x):
            for f in dataclasses.fields(x):
                walk(getattr(x, f.name), f"{where}.{f.name}")
        elif isinstance(x, (list, tuple)):
            for k, y in enumerate(x):
                walk(y, f"{where}[{k}]")
        elif isinstance(x, np.ndarray):
            assert x.dtype != object, where

    for k, r in enumerate(records):
        walk(r, f"record {k}")


def test_a_record_round_trips_through_save_and_load(kept, tmp_path):
    model, records = kept
    path = save_records(model, tmp_path / "run" / "counterplay.zip")
    assert path == tmp_path / "run" / "counterplay.searches.npz" == searches_path(tmp_path / "run" / "counterplay.zip")
    back = load_records(path)
    assert len(back) == len(records)
    for k, (a, b) in enumerate(zip(records, back)):
        _assert_same(a, b, f"record {k}")
    # the figure of a loaded record is the figure of the kept one
    assert format_table(back) == format_table(records)
    assert not list(tmp_path.glob("run/.*")), "temp files left behind"


def test_load_rejects_what_is_not_a_search_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_records(tmp_path / "none.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(2))
    with pytest.raises(ValueError, match="not a CounterPlay search file"):
        load_records(tmp_path / "other.npz")


def test_the_store_keeps_the_most_informative_latest_searches(kept):
    _, records = kept
    verified, discarded = _by_status(records, "verified"), _by_status(records, "discarded")
    nothing = dataclasses.replace(discarded, chosen=None, verified=None)
    store = SearchRecords(per_generation=2, max_records=3)
    for r in (verified, nothing, discarded, nothing, nothing):
        store.add(dataclasses.replace(r, generation=0))
    assert [r.status for r in store] == ["verified", "discarded"]  # not the last two
    for r in (nothing, nothing):
        store.add(dataclasses.replace(r, generation=1))
    assert len(store) == 3 and [r.generation for r in store] == [0, 0, 1]  # max_records: the least informative go
    assert store.latest("verified").status == "verified" and store.latest().generation == 1


def test_keep_searches_is_validated():
    env = make_env()
    for bad in (-1, 2.5, "x", None):
        with pytest.raises(ValueError, match="keep_searches"):
            make_model(env, keep_searches=bad)


def test_keep_searches_zero_keeps_nothing_and_retains_no_tensors(monkeypatch):
    force_teachers(monkeypatch)

    def no_records(*args, **kwargs):
        raise AssertionError("a record was built with keep_searches=0")

    monkeypatch.setattr(records_module, "build_record", no_records)
    model = run_generations(make_model(keep_searches=0))
    totals = model.search_totals
    assert totals["searches"] > 0 and totals["teachers_chosen"] > 0
    assert "_search_records" not in model.__dict__ and len(search_records(model)) == 0
    gc.collect()
    assert not [o for o in gc.get_objects() if type(o) is BranchResult], "branch results outlive the search"


def test_kept_searches_do_not_keep_branch_results_alive(kept):
    gc.collect()
    assert not [o for o in gc.get_objects() if type(o) is BranchResult]


def test_kept_searches_stay_out_of_the_checkpoint(kept, tmp_path):
    model, records = kept
    model.save(tmp_path / "cp")
    loaded = CounterPlay.load(tmp_path / "cp.zip", device="cpu")
    assert loaded.keep_searches == 8 and len(search_records(loaded)) == 0


# ---------------------------------------------------------------------------- figures
@pytest.mark.parametrize("status", ["verified", "discarded"])
def test_the_figure_renders_with_one_line_per_branch(kept, tmp_path, status):
    _, records = kept
    r = _by_status(records, status)
    fig = plot_search(r)
    lines = [ln for ax in fig.axes for ln in ax.get_lines() if str(ln.get_gid()).startswith("branch:")]
    assert sorted(ln.get_gid() for ln in lines) == sorted(f"branch:{b.name}" for b in r.branches)
    chosen = next(ln for ln in lines if ln.get_gid() == f"branch:{r.teacher}")
    assert chosen.get_linewidth() > max(ln.get_linewidth() for ln in lines if ln is not chosen)
    labels = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    for name in r.panel:
        assert any(label.startswith(f"{name}:") for label in labels), name
    assert any(("verified" if status == "verified" else "failed verification") in label for label in labels)
    png = render_search(r, tmp_path / f"{status}.png")
    assert png.stat().st_size > 10_000


def test_the_figure_renders_a_single_style_panel_with_repeated_names(kept, tmp_path):
    """cp-only-<style> panels repeat one style: branch traces share a name and are ordered by
    identity, not by == (which would compare their arrays)."""
    _, records = kept
    r = _by_status(records, "verified")
    style = r.panel[0]
    branches = [dataclasses.replace(b, name=style if b.kind == "candidate" else b.name) for b in r.branches]
    single = dataclasses.replace(r, panel=(style,) * len(r.panel), branches=branches)
    fig = plot_search(single)
    lines = [ln for ax in fig.axes for ln in ax.get_lines() if str(ln.get_gid()).startswith("branch:")]
    assert len(lines) == len(branches)
    assert render_search(single, tmp_path / "single.png").stat().st_size > 10_000


def test_the_animation_shows_factual_and_retry_side_by_side(kept, tmp_path):
    _, records = kept
    r = _by_status(records, "verified")
    frames = animate_search(r, tmp_path / "search.gif", hold_s=0.0)
    assert len(frames) == max(r.factual.length, r.chosen_branch.length) + 1
    assert frames[0].ndim == 3 and frames[0].dtype == np.uint8
    assert not np.array_equal(frames[0], frames[-1])
    assert (tmp_path / "search.gif").stat().st_size > 0
    with pytest.raises(ValueError, match="extension"):
        render_search(r, tmp_path / "x.txt")


# ---------------------------------------------------------------------------- anatomy
def test_failure_anatomy_counts_what_the_searched_failures_were(kept):
    _, records = kept
    a = failure_anatomy(records)
    assert a["searches"] == len(records)
    assert sum(a[k] for k in ("timeout", "collision", "offroad", "goal")) == len(records)
    assert a["decisions_after_root_median"] == np.median([r.factual.length for r in records])
    assert 0.0 <= a["candidates_completed"] <= 1.0
    assert "decisions before the end" in format_anatomy(a)
    assert a["roots_at_reset"] == sum(r.root_step == 0 for r in records)
    assert a["verified"] == sum(bool(r.verified) for r in records)
    # a verified search whose fresh factual rerun completes counts as a failure that did not recur
    r = _by_status(records, "verified")
    verify = [dataclasses.replace(b, outcome="goal" if b.kind == "verify-factual" else b.outcome)
              for b in r.branches]
    assert any(b.kind == "verify-factual" for b in verify)
    recurred = dataclasses.replace(r, branches=[dataclasses.replace(b, outcome="collision")
                                                if b.kind == "verify-factual" else b for b in r.branches])
    lucky = failure_anatomy([dataclasses.replace(r, branches=verify), recurred])
    assert (lucky["verified"], lucky["verified_factual_completed"]) == (2, 1)
    assert "the fresh draws too: 50%" in format_anatomy(lucky)
    unverified = failure_anatomy([dataclasses.replace(r, branches=verify, verified=False)])
    assert (unverified["verified"], unverified["verified_factual_completed"]) == (0, 0)
    # hand-made factual timeouts of one record: through the goal at 2 m spacing, then parked 30 m away
    r = next(r for r in records if r.factual.length >= 2)
    f, focal = r.factual, r.focal
    n = f.xy.shape[0]
    valid = f.valid.copy()
    valid[:, focal] = True

    def with_path(path):
        xy = f.xy.copy()
        xy[:, focal] = path
        fact = dataclasses.replace(f, xy=xy, valid=valid, outcome="timeout")
        return dataclasses.replace(r, branches=[fact if b is f else b for b in r.branches], goal_radius=2.0)

    goal = r.goal[focal]
    through = goal[None] + np.stack([3.0 * (np.arange(n) - n // 2), np.full(n, 0.5)], -1)  # 3 m steps
    one = failure_anatomy([with_path(through.astype(np.float32))])
    assert (one["timeout"], one["timeout_passed_goal"], one["timeout_stuck"]) == (1, 1, 0)
    parked = np.repeat((goal + 30.0)[None], n, 0).astype(np.float32)
    one = failure_anatomy([with_path(parked)])
    assert (one["timeout"], one["timeout_passed_goal"], one["timeout_stuck"]) == (1, 0, 1)


# ---------------------------------------------------------------------------- command
def test_the_searches_command_lists_what_was_kept(kept, tmp_path, capsys):
    model, records = kept
    save_records(model, tmp_path / "counterplay.zip")
    assert cli.main(["searches", "--model", str(tmp_path / "counterplay.zip")]) == 0
    out = capsys.readouterr().out
    assert f"{len(records)} searches kept" in out
    table = out.splitlines()[1:]
    header = table[0].split()
    for column in ("scenario", "failure", "depth", "admissible", "teacher", "verified"):
        assert column in header
    rows, anatomy = table[2:-3], table[-3:]
    assert len(rows) == len(records)
    assert anatomy[0].startswith("factual failures:") and anatomy[1].startswith("roots: median")
    assert anatomy[2].startswith("verified teachers:")
    for k, (row, r) in enumerate(zip(rows, records)):
        cells = row.split()
        assert cells[0] == str(k) and r.scenario_id in cells
        assert f"{r.failure}@{r.failure_step}" in cells and str(r.depth) in cells
        assert cells[-1] == {"verified": "yes", "discarded": "no"}.get(r.status, "-")
    k = next(k for k, r in enumerate(records) if r.status == "verified")
    for name in ("fig.png", "fig.gif"):
        assert cli.main(["searches", "--model", str(tmp_path / "counterplay.searches.npz"), "--show", str(k),
                         "--out", str(tmp_path / name)]) == 0
        assert (tmp_path / name).stat().st_size > 0
    capsys.readouterr()
    for argv, message in ((["--model", str(tmp_path / "counterplay.zip"), "--show", str(len(records))], "--show"),
                          (["--model", str(tmp_path / "missing.zip")], "no search file")):
        with pytest.raises(SystemExit) as exc:  # usage errors: one line, exit status 2
            cli.main(["searches", *argv])
        assert exc.value.code == 2 and message in capsys.readouterr().err


def test_the_main_job_writes_the_figure_of_a_verified_search(kept, tmp_path):
    model, records = kept
    # what a run of the main job (cpalgo.experiments.runs.train_run) and `post-train` write
    files = write_search_files(model, tmp_path / "run" / "model.zip")
    assert files["searches"] == str(tmp_path / "run" / "model.searches.npz")
    assert files["figure"] == str(tmp_path / "run" / "search.png")
    assert (tmp_path / "run" / "search.png").stat().st_size > 10_000
    assert len(load_records(files["searches"])) == len(records)
    assert cli._write_searches(model, tmp_path / "counterplay.zip")["figure"] == str(tmp_path / "search.png")
    assert write_search_files(make_model(keep_searches=0), tmp_path / "none.zip") == {}


def test_a_counterfactual_run_that_kept_no_search_still_gets_its_search_file(tmp_path, capsys):
    model = make_model()  # nothing learned yet: no search kept
    files = write_search_files(model, tmp_path / "counterplay.zip")
    assert files == {"searches": str(tmp_path / "counterplay.searches.npz")} and load_records(files["searches"]) == []
    capsys.readouterr()
    assert cli.main(["searches", "--model", str(tmp_path / "counterplay.zip")]) == 0
    assert "0 searches kept" in capsys.readouterr().out
