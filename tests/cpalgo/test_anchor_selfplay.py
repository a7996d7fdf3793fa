"""The resumable self-play anchor run (cpalgo.anchor.selfplay): pieces equal one run, a
killed piece loses only its unsaved segment, the curve and its plot, and clear errors."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch as th

from cpalgo.anchor import selfplay
from cpalgo.anchor.selfplay import AnchorRunSettings, plot_curve, read_curve, train_anchor_run

RECIPE = """cpsim/SelfPlay-v0:
  policy: 'BehaviorLstmPolicy'
  n_envs: 8
  n_timesteps: 300
  n_steps: 8
  batch_size: 32
  n_epochs: 1
  learning_rate: 'cosine(1e-3)'
  clip_reward: 1.0
  policy_kwargs: "dict(lstm_hidden_size=16, features_extractor_kwargs=dict(ego_width=8, condition_width=8, partner_width=8, road_width=8, features_dim=16))"
  env_kwargs:
    max_agents: 4
    dynamics: classic
"""


@pytest.fixture()
def recipe(tmp_path: Path) -> str:
    path = tmp_path / "tiny.yml"
    path.write_text(RECIPE)
    return str(path)


def _settings(recipe: str) -> AnchorRunSettings:
    return AnchorRunSettings(recipe=recipe, seed=3, timesteps=300, segment_timesteps=100, pool_size=2, eval_tasks=2)


def _weights(run: Path) -> dict[str, th.Tensor]:
    with zipfile.ZipFile(run / "checkpoint.zip") as archive:
        return th.load(io.BytesIO(archive.read("policy.pth")), weights_only=False)


def _optimizer(run: Path) -> dict:
    with zipfile.ZipFile(run / "checkpoint.zip") as archive:
        return th.load(io.BytesIO(archive.read("policy.optimizer.pth")), weights_only=False)


def _same(a: dict[str, th.Tensor], b: dict[str, th.Tensor]) -> bool:
    return a.keys() == b.keys() and all(th.equal(a[k], b[k]) for k in a)


def _quiet(_msg: str) -> None:
    pass


def test_pieces_and_a_killed_piece_equal_one_uninterrupted_run(tmp_path: Path, recipe: str, monkeypatch):
    # the uninterrupted run builds each next segment's env and evaluates each checkpoint in a
    # worker process, the pieces do both in place: same pools, same arrays, same run, same curve
    messages: list[str] = []
    whole = train_anchor_run(tmp_path / "whole", _settings(recipe), log=messages.append, worker=True)
    assert sum("(prepared ahead)" in m for m in messages) == 2, messages  # segments 1 and 2
    rows = read_curve(tmp_path / "whole")
    assert [int(r["segment"]) for r in rows] == list(range(len(rows))) and len(rows) >= 3
    assert rows[-1]["timesteps"] >= 300 > rows[-2]["timesteps"]
    assert whole.num_timesteps == rows[-1]["timesteps"]
    # every segment updated the policy at least once: its update statistics are logged
    assert all(r["approx_kl"] >= 0 and 0 <= r["clip_fraction"] <= 1 and 0 < r["entropy"] <= np.log(91) + 1e-6
               and r["value_loss"] > 0 for r in rows)
    with zipfile.ZipFile(tmp_path / "whole" / "checkpoint.zip") as archive:
        assert '"_last_obs": null' in archive.read("data").decode()  # not needed to resume

    # piece 1 stops after its first segment ...
    train_anchor_run(tmp_path / "pieces", _settings(recipe), stop_after_s=0.0, log=_quiet, worker=False)
    assert len(read_curve(tmp_path / "pieces")) == 1
    # ... piece 2 is killed after learning its first segment, before the checkpoint
    calls = {"n": 0}
    real_evaluate = selfplay._evaluate

    def killed(*args, **kwargs):
        calls["n"] += 1
        raise KeyboardInterrupt("killed")

    monkeypatch.setattr(selfplay, "_evaluate", killed)
    kept = _weights(tmp_path / "pieces")
    with pytest.raises(KeyboardInterrupt):
        train_anchor_run(tmp_path / "pieces", resume=True, log=_quiet, worker=False)
    assert calls["n"] == 1 and _same(_weights(tmp_path / "pieces"), kept)  # the last checkpoint survives
    monkeypatch.setattr(selfplay, "_evaluate", real_evaluate)
    # ... piece 3 resumes from the last checkpoint and finishes
    resumed = train_anchor_run(tmp_path / "pieces", resume=True, log=_quiet, worker=False)
    assert resumed.num_timesteps == whole.num_timesteps
    assert _same(_weights(tmp_path / "pieces"), _weights(tmp_path / "whole"))
    opt_a, opt_b = _optimizer(tmp_path / "pieces"), _optimizer(tmp_path / "whole")
    assert all(th.equal(opt_a["state"][k]["exp_avg"], opt_b["state"][k]["exp_avg"]) for k in opt_a["state"])
    piece_rows = read_curve(tmp_path / "pieces")
    # the same curve, wall time apart (nan where a segment ended no training episode)
    np.testing.assert_equal([{k: v for k, v in r.items() if k != "wall_s"} for r in piece_rows],
                            [{k: v for k, v in r.items() if k != "wall_s"} for r in rows])
    # the learning rate followed one cosine over the whole budget
    assert rows[0]["learning_rate"] > rows[1]["learning_rate"] > rows[2]["learning_rate"]
    table = selfplay.curve_table(rows, every=2).splitlines()
    # header, rule, every second segment and the last
    assert len(table) == 2 + len(range(1, len(rows), 2)) + (len(rows) % 2) and table[-1].startswith(
        f"| {rows[-1]['timesteps'] / 1e6:.1f}M |")
    assert f"{100 * rows[-1]['normal_goal']:.1f}" in table[-1]
    png = plot_curve(tmp_path / "whole")
    assert png.is_file() and png.stat().st_size > 1000
    # while a piece runs, its last row waits for the worker's evaluation: plot and table still draw
    partial = {k: rows[-1][k] for k in ("segment", "timesteps", "wall_s", "train_goal")}
    (tmp_path / "partial").mkdir()
    selfplay._write_curve(tmp_path / "partial", [*rows, partial])
    assert plot_curve(tmp_path / "partial").is_file()
    assert "| - / - / - |" in selfplay.curve_table(read_curve(tmp_path / "partial")).splitlines()[-1]


def test_curve_rise_fits_the_last_third(tmp_path: Path, capsys):
    from cpalgo import cli

    # 30 points, 10M apart: flat at 0.80 up to 200M, then +0.5 points per 10M to 300M
    rows = [{"segment": i, "timesteps": 10e6 * (i + 1), "wall_s": 60.0 * (i + 1),
             "normal_goal": 0.80 + (0.005 * (i - 19) if i > 19 else 0.0),
             "aggressive_goal": 0.9, "cautious_goal": 0.7} for i in range(30)]
    rise = selfplay.curve_rise(rows)
    assert rise["start"] == pytest.approx(200e6) and rise["end"] == 300e6 and rise["points"] == 11
    assert rise["rise"] == pytest.approx(0.05) and rise["first"] < rise["last"] == pytest.approx(0.8475)
    flat = [dict(r, normal_goal=0.8 + (0.02 if i % 2 else -0.02)) for i, r in enumerate(rows)]
    assert abs(selfplay.curve_rise(flat)["rise"]) < 0.01  # noise around a level is no rise
    with pytest.raises(ValueError, match="1 evaluated point"):
        selfplay.curve_rise(rows[:2])
    with pytest.raises(ValueError, match="share: expected"):
        selfplay.curve_rise(rows, share=0.0)
    # the CLI prints it beside the last evaluated point, a row still waiting for its evaluation apart
    run = tmp_path / "run"
    run.mkdir()
    selfplay._write_curve(run, [*rows, {"segment": 30, "timesteps": 310e6, "wall_s": 1900.0}])
    assert cli.main(["curve", str(run)]) == 0
    out = capsys.readouterr().out
    assert "last at 310.0M" in out and "90.0% / 85.0% / 70.0% at 300.0M" in out and "rose +5.0 points" in out


def test_run_folder_errors_name_the_folder(tmp_path: Path, recipe: str):
    with pytest.raises(ValueError, match="holds no run.json"):
        train_anchor_run(tmp_path / "nothing", resume=True, log=_quiet)
    with pytest.raises(ValueError, match="segment_timesteps"):
        AnchorRunSettings(recipe=recipe, segment_timesteps=0)
    with pytest.raises(ValueError, match="unknown settings"):
        AnchorRunSettings.from_dict({"recipe": recipe, "epochs": 3})
    with pytest.raises(ValueError, match="has no curve.csv"):
        read_curve(tmp_path)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "run.json").write_text("{}")
    with pytest.raises(ValueError, match="already holds a run"):
        train_anchor_run(tmp_path / "run", _settings(recipe), log=_quiet)


def test_a_resumed_piece_changes_ppo_settings_and_records_them(tmp_path: Path, recipe: str):
    import json

    run = tmp_path / "run"
    train_anchor_run(run, _settings(recipe), stop_after_s=0.0, log=_quiet, worker=False)
    model = train_anchor_run(run, resume=True, stop_after_s=0.0, log=_quiet, worker=False,
                             changes=["ent_coef=0.03", "learning_rate=cosine(2e-3)", "n_epochs=2", "gamma=0.995"])
    assert model.ent_coef == 0.03 and model.n_epochs == 2
    assert model.gamma == 0.995 and model.rollout_buffer.gamma == 0.995  # the returns use it
    rows = read_curve(run)
    # the new cosine, over the same whole budget: 2e-3 at the start, 1e-3 half way
    assert model.lr_schedule(1.0) == pytest.approx(2e-3) and model.lr_schedule(0.5) == pytest.approx(1e-3)
    # the second segment trained with it: its last update's rate is the new cosine's at that point
    from cpalgo.recipes import CosineSchedule

    assert rows[1]["learning_rate"] == pytest.approx(CosineSchedule(2e-3)(1 - rows[1]["timesteps"] / 300), rel=1e-6)
    doc = json.loads((run / "run.json").read_text())
    assert doc["changes"] == [{"segment": 1, "timesteps": int(rows[0]["timesteps"]),
                               "set": {"ent_coef": 0.03, "learning_rate": "cosine(2e-3)", "n_epochs": 2,
                                       "gamma": 0.995}}]
    # the checkpoint carries the change into the next piece
    model = train_anchor_run(run, resume=True, stop_after_s=0.0, log=_quiet, worker=False)
    assert model.ent_coef == 0.03 and model.n_epochs == 2
    assert model.gamma == 0.995 and model.rollout_buffer.gamma == 0.995

    for bad, match in ((["batch_size=64"], "'batch_size' cannot be changed"), (["ent_coef"], "KEY=VALUE"),
                       (["ent_coef=-1"], "ent_coef must be a finite number >= 0"),
                       (["learning_rate=fast"], "learning_rate"), (["n_epochs=0.5"], "n_epochs"),
                       (["gamma=1.5"], r"gamma must be a finite number in \[0, 1\]")):
        with pytest.raises(ValueError, match=match):
            train_anchor_run(run, resume=True, log=_quiet, changes=bad)
    with pytest.raises(ValueError, match="only in a resumed run"):
        train_anchor_run(tmp_path / "new", _settings(recipe), log=_quiet, changes=["ent_coef=0.1"])
    assert json.loads((run / "run.json").read_text())["changes"] == doc["changes"]  # nothing half-written


def test_a_resumed_piece_changes_env_settings_and_later_pieces_keep_them(tmp_path: Path, recipe: str, monkeypatch):
    import json

    built: list[dict] = []
    original = selfplay._build_env

    def recording(*args, **kwargs):
        env = original(*args, **kwargs)
        built.append({"timeout_terminal": env.venv.timeout_terminal, "threads": th.get_num_threads()})
        return env

    monkeypatch.setattr(selfplay, "_build_env", recording)
    threads = th.get_num_threads()
    try:
        run = tmp_path / "run"
        train_anchor_run(run, _settings(recipe), stop_after_s=0.0, log=_quiet, worker=False)
        train_anchor_run(run, resume=True, stop_after_s=0.0, log=_quiet, worker=False,
                         changes=["timeout_terminal=true", "threads=1"])
        doc = json.loads((run / "run.json").read_text())
        assert doc["changes"][-1]["set"] == {"timeout_terminal": True, "threads": 1}
        assert doc["settings"]["threads"] is None  # the run's settings stay as started; changes apply over them
        # a later piece without --set still builds its envs with the change
        train_anchor_run(run, resume=True, stop_after_s=0.0, log=_quiet, worker=False)
        assert [b["timeout_terminal"] for b in built] == [False, True, True]
        assert built[1]["threads"] == 1 and built[2]["threads"] == 1
        assert selfplay.env_changes(doc) == {"timeout_terminal": True}
        for bad, match in ((["timeout_terminal=yes"], "true or false"), (["eval_task_share=1.5"], r"in \[0, 1\]"),
                           (["threads=0"], "threads must be a whole number")):
            with pytest.raises(ValueError, match=match):
                train_anchor_run(run, resume=True, log=_quiet, changes=bad)
    finally:
        th.set_num_threads(threads)


def test_a_piece_killed_before_its_last_evaluation_is_completed_by_the_next(tmp_path: Path, recipe: str, monkeypatch):
    whole = tmp_path / "whole"
    train_anchor_run(whole, _settings(recipe), log=_quiet, worker=False)

    def killed(self):
        raise KeyboardInterrupt("killed while the worker evaluates")

    run = tmp_path / "run"
    monkeypatch.setattr(selfplay._SegmentWorker, "evaluation", killed)
    with pytest.raises(KeyboardInterrupt):
        train_anchor_run(run, _settings(recipe), stop_after_s=0.0, log=_quiet, worker=True)
    rows = read_curve(run)
    assert len(rows) == 1 and "normal_goal" not in rows[0]  # trained and saved, not evaluated
    monkeypatch.undo()
    messages: list[str] = []
    train_anchor_run(run, resume=True, log=messages.append, worker=False)
    assert messages[1].startswith("segment 0 (evaluated here")
    np.testing.assert_equal([{k: v for k, v in r.items() if k != "wall_s"} for r in read_curve(run)],
                            [{k: v for k, v in r.items() if k != "wall_s"} for r in read_curve(whole)])


def _two_worker_settings(recipe: str, timesteps: int = 200) -> AnchorRunSettings:
    # 4 worlds x 4 slots: 2 worlds per worker, minibatches of 16 live transitions each
    return AnchorRunSettings(recipe=recipe, seed=3, timesteps=timesteps, segment_timesteps=100, pool_size=2,
                             eval_tasks=2, workers=2)


@pytest.fixture()
def four_worlds(tmp_path: Path) -> str:
    path = tmp_path / "four_worlds.yml"
    path.write_text(RECIPE.replace("n_envs: 8", "n_envs: 16"))
    return str(path)


def test_two_workers_pieces_equal_one_uninterrupted_run(tmp_path: Path, four_worlds: str):
    import json

    # the uninterrupted run prepares each next segment in rank 0's worker (rank 1 adopts it)
    messages: list[str] = []
    whole = train_anchor_run(tmp_path / "whole", _two_worker_settings(four_worlds), log=messages.append, worker=True)
    assert sum("(prepared ahead)" in m for m in messages) == 1, messages  # segment 1
    rows = read_curve(tmp_path / "whole")
    assert len(rows) == 2 and rows[-1]["timesteps"] >= 200 > rows[0]["timesteps"] >= 100
    assert whole.num_timesteps == rows[-1]["timesteps"] and whole.batch_size == 16  # 32 over 2 workers
    assert whole.n_envs == 2 * 4  # each worker steps 2 of the 4 worlds
    assert len(whole.resume_state["rank_rng"]) == 2
    assert whole.budget.main == whole.num_timesteps  # the budget counts every rank's transitions too
    assert json.loads((tmp_path / "whole" / "run.json").read_text())["settings"]["workers"] == 2

    pieces = tmp_path / "pieces"
    train_anchor_run(pieces, _two_worker_settings(four_worlds), stop_after_s=0.0, log=_quiet, worker=False)
    assert len(read_curve(pieces)) == 1
    with pytest.raises(ValueError, match="--workers: the run .* runs with 2 worker"):
        train_anchor_run(pieces, resume=True, workers=1, log=_quiet, worker=False)
    resumed = train_anchor_run(pieces, resume=True, workers=2, log=_quiet, worker=False)
    assert resumed.num_timesteps == whole.num_timesteps
    assert _same(_weights(pieces), _weights(tmp_path / "whole"))
    opt_a, opt_b = _optimizer(pieces), _optimizer(tmp_path / "whole")
    assert all(th.equal(opt_a["state"][k]["exp_avg_sq"], opt_b["state"][k]["exp_avg_sq"]) for k in opt_a["state"])
    np.testing.assert_equal([{k: v for k, v in r.items() if k != "wall_s"} for r in read_curve(pieces)],
                            [{k: v for k, v in r.items() if k != "wall_s"} for r in rows])


def test_workers_must_divide_the_worlds_and_the_minibatch(tmp_path: Path, four_worlds: str, recipe: str):
    import dataclasses

    with pytest.raises(ValueError, match="--workers: 3 does not divide the recipe's 4 worlds"):
        train_anchor_run(tmp_path / "three", dataclasses.replace(_two_worker_settings(four_worlds), workers=3),
                         log=_quiet)
    assert not (tmp_path / "three").exists()  # rejected before anything is written
    odd = tmp_path / "odd_batch.yml"
    odd.write_text(Path(four_worlds).read_text().replace("batch_size: 32", "batch_size: 30"))
    with pytest.raises(ValueError, match="--workers: 4 does not divide the recipe's batch_size 30"):
        train_anchor_run(tmp_path / "four", dataclasses.replace(_two_worker_settings(str(odd)), workers=4),
                         log=_quiet)
    with pytest.raises(ValueError, match="workers: expected a whole number >= 1"):
        AnchorRunSettings(recipe=recipe, workers=0)
    # a one-worker run resumes with one worker unless a change says otherwise
    train_anchor_run(tmp_path / "one", _settings(recipe), stop_after_s=0.0, log=_quiet, worker=False)
    with pytest.raises(ValueError, match="--workers: the run .* runs with 1 worker.*--set workers=N"):
        train_anchor_run(tmp_path / "one", resume=True, workers=2, log=_quiet)
    with pytest.raises(ValueError, match="workers must be a whole number >= 1"):
        train_anchor_run(tmp_path / "one", resume=True, changes=["workers=0"], log=_quiet)


def test_a_resumed_run_changes_its_worker_count(tmp_path: Path, four_worlds: str):
    import dataclasses
    import json

    run = tmp_path / "run"
    one = dataclasses.replace(_two_worker_settings(four_worlds, timesteps=300), workers=1)
    first = train_anchor_run(run, one, stop_after_s=0.0, log=_quiet, worker=False)
    assert first.batch_size == 32 and first.n_envs == 4 * 4 and "rank_rng" not in first.resume_state
    # the next piece trains on two ranks from the one-worker checkpoint (rank 1 seeded anew)
    two = train_anchor_run(run, resume=True, changes=["workers=2"], stop_after_s=0.0, log=_quiet, worker=False)
    assert two.batch_size == 16 and two.n_envs == 2 * 4 and len(two.resume_state["rank_rng"]) == 2
    assert two.num_timesteps > first.num_timesteps and len(read_curve(run)) == 2
    changes = json.loads((run / "run.json").read_text())["changes"]
    assert changes[-1]["set"] == {"workers": 2}
    # later pieces keep the recorded count: --workers 2 agrees with it, 1 does not
    with pytest.raises(ValueError, match="--workers: the run .* runs with 2 worker"):
        train_anchor_run(run, resume=True, workers=1, log=_quiet, worker=False)
    third = train_anchor_run(run, resume=True, workers=2, stop_after_s=0.0, log=_quiet, worker=False)
    assert third.batch_size == 16 and third.n_envs == 2 * 4 and len(read_curve(run)) == 3


def test_workers_times_threads_may_not_exceed_the_cores(tmp_path: Path, four_worlds: str, monkeypatch):
    import dataclasses
    import json
    import os

    # two 2-thread ranks on 2 cores spin-wait on each other: a piece ran many times slower than one process
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    with pytest.raises(ValueError, match="threads: 2 torch threads in each of 2 workers exceed this machine's 2 cores"):
        train_anchor_run(tmp_path / "new", dataclasses.replace(_two_worker_settings(four_worlds), threads=2),
                         log=_quiet)
    assert not (tmp_path / "new").exists()
    run = tmp_path / "run"
    one = dataclasses.replace(_two_worker_settings(four_worlds, timesteps=300), workers=1, threads=2)
    train_anchor_run(run, one, stop_after_s=0.0, log=_quiet, worker=False)
    commands = (run / "commands.txt").read_text() if (run / "commands.txt").exists() else ""
    with pytest.raises(ValueError, match="threads: 2 torch threads in each of 2 workers.*--set threads=N"):
        train_anchor_run(run, resume=True, changes=["workers=2"], log=_quiet, worker=False, command="resume")
    assert "changes" not in json.loads((run / "run.json").read_text())  # nothing recorded
    assert ((run / "commands.txt").read_text() if (run / "commands.txt").exists() else "") == commands
    two = train_anchor_run(run, resume=True, changes=["workers=2", "threads=1"], stop_after_s=0.0, log=_quiet,
                           worker=False)
    assert two.n_envs == 2 * 4 and len(two.resume_state["rank_rng"]) == 2


def test_the_cli_reports_a_bad_workers_count_as_a_usage_error(tmp_path: Path, four_worlds: str, capsys):
    from cpalgo import cli

    for argv, message in ((["--run-dir", str(tmp_path / "run"), "--config", four_worlds, "--workers", "3"],
                           "--workers: 3 does not divide the recipe's 4 worlds"),
                          (["--config", four_worlds, "--out", str(tmp_path / "a.zip"), "--workers", "2"],
                           "--workers: only with --run-dir / --resume")):
        capsys.readouterr()
        with pytest.raises(SystemExit) as exc:
            cli.main(["train-anchor", *argv])
        assert exc.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_train_anchor_recipe_defaults_follow_the_mode(tmp_path: Path, monkeypatch):
    """Without --config, a --run-dir run trains on the self-play anchor's recipe and the
    one-checkpoint path on the teacher-imitation anchor's."""
    from cpalgo import cli
    from cpalgo.cli import anchor as anchor_cli
    from cpalgo.recipes import load_recipe

    seen: dict[str, object] = {}
    monkeypatch.setattr(selfplay, "train_anchor_run", lambda run_dir, settings, **_: seen.update(settings=settings))
    assert cli.main(["train-anchor", "--run-dir", str(tmp_path / "run")]) == 0
    assert seen["settings"].recipe == load_recipe("zoo/anchor_selfplay.yml").path
    assert seen["settings"].timesteps == 300_000_000   # the recipe's n_timesteps

    def stop(algorithm_class, recipe):
        seen["recipe"] = recipe.path
        raise cli.UsageError("stop here")

    monkeypatch.setattr(anchor_cli, "check_algorithm_arguments", stop)
    with pytest.raises(SystemExit):
        cli.main(["train-anchor", "--out", str(tmp_path / "a.zip")])
    assert seen["recipe"] == load_recipe("zoo/anchor.yml").path
