"""``counterplay export-anchor`` (cpalgo.anchor.export): a run's checkpoint without the resume
state loads as usual and acts the same, its record says where it came from, and bad input is
refused before anything is written."""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch as th

from cpalgo.anchor.export import HELD_OUT_ROWS, export_anchor
from cpalgo.anchor.selfplay import AnchorRunSettings, read_curve, train_anchor_run
from tests.cpalgo.test_anchor_selfplay import RECIPE

COMMANDS = ("counterplay train-anchor --config tiny.yml --run-dir run", "counterplay train-anchor --resume run")


def _quiet(_msg: str) -> None:
    pass


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A two-piece run of the tiny recipe (one segment each, the second with a change)."""
    folder = tmp_path_factory.mktemp("export")
    recipe = folder / "tiny.yml"
    recipe.write_text(RECIPE)
    settings = AnchorRunSettings(recipe=str(recipe), seed=3, timesteps=300, segment_timesteps=100, pool_size=2,
                                 eval_tasks=2)
    train_anchor_run(folder / "run", settings, stop_after_s=0.0, log=_quiet, worker=False, command=COMMANDS[0])
    train_anchor_run(folder / "run", resume=True, stop_after_s=0.0, log=_quiet, worker=False, command=COMMANDS[1],
                     changes=["ent_coef=0.02"])
    return folder / "run"


def _entry(path: Path, name: str) -> bytes:
    with zipfile.ZipFile(path) as archive:
        return archive.read(name)


def _actions(model, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sampled actions over 4 recurrent steps (torch seeded) and the first step's probabilities."""
    th.manual_seed(7)
    state, actions = None, []
    for t in range(4):
        starts = np.full(len(obs), t == 0)
        action, state = model.predict(obs + 0.1 * t, state=state, episode_start=starts, deterministic=False)
        actions.append(action)
    lstm = model.policy.lstm_actor
    zeros = th.zeros((lstm.num_layers, len(obs), lstm.hidden_size))
    with th.no_grad():
        dist, _ = model.policy.get_distribution(th.as_tensor(obs), (zeros, zeros.clone()), th.ones(len(obs)))
    return np.stack(actions), dist.distribution.probs.numpy()


def test_the_export_loads_acts_the_same_and_drops_the_resume_state(run: Path, tmp_path: Path):
    from cpalgo.evaluate.runner import load_model

    source = run / "checkpoint.zip"
    before = source.read_bytes()
    out, record_path = tmp_path / "ship" / "anchor.zip", tmp_path / "ship" / "anchor.json"
    record = export_anchor(run, out, record_path)
    assert source.read_bytes() == before  # the run is only read
    assert out.stat().st_size < 0.6 * len(before)

    original, exported = load_model(source), load_model(out)
    assert type(exported) is type(original) and exported.num_timesteps == original.num_timesteps
    a, b = original.policy.state_dict(), exported.policy.state_dict()
    assert a.keys() == b.keys() and all(th.equal(a[k], b[k]) for k in a)
    assert _entry(out, "policy.pth") == _entry(source, "policy.pth")  # the weights' bytes too
    obs = np.random.default_rng(0).standard_normal((16, original.observation_space.shape[0])).astype(np.float32)
    (acts_a, probs_a), (acts_b, probs_b) = _actions(original, obs), _actions(exported, obs)
    np.testing.assert_array_equal(acts_a, acts_b)
    np.testing.assert_array_equal(probs_a, probs_b)
    assert exported.ent_coef == original.ent_coef == 0.02  # the run's changes travel with it

    # no Adam moments (the optimiser's settings stay), no resume state, no per-generation log
    optimizer = th.load(io.BytesIO(_entry(out, "policy.optimizer.pth")), weights_only=False)
    assert optimizer["state"] == {} and optimizer["param_groups"][0]["betas"] == (0.9, 0.999)
    assert th.load(io.BytesIO(_entry(source, "policy.optimizer.pth")), weights_only=False)["state"]
    data = json.loads(_entry(out, "data"))
    assert "resume_state" not in data and "resume_state" in json.loads(_entry(source, "data"))
    assert not hasattr(exported, "resume_state") and exported.budget.history == []
    assert exported.budget.main == original.budget.main
    # post-training and --init load it with exact_match (they need the optimiser entry)
    original.set_parameters(str(out), exact_match=True, device="cpu")

    # the record
    assert json.loads(record_path.read_text()) == record
    json.loads(record_path.read_text(), parse_constant=lambda c: pytest.fail(f"{c} in the record"))
    written = out.read_bytes()
    assert record["anchor"] == {"path": str(out), "bytes": len(written), "sha256": hashlib.sha256(written).hexdigest()}
    assert record["source"]["sha256"] == hashlib.sha256(before).hexdigest()
    doc = json.loads((run / "run.json").read_text())
    assert record["settings"] == doc["settings"] and record["changes"] == doc["changes"]
    assert record["changes"][0]["set"] == {"ent_coef": 0.02}
    assert record["commands"] == list(COMMANDS)
    assert record["recipe"]["text"] == (run / "recipe.yml").read_text()
    assert record["recipe"]["path"] == doc["settings"]["recipe"]
    rows = read_curve(run)
    assert record["num_timesteps"] == original.num_timesteps == rows[-1]["timesteps"]
    assert record["segments"] == len(rows) == 2 and record["training_wall_s"] == rows[-1]["wall_s"]
    assert record["network"] == {"policy_class": "cpalgo.policies.behavior.BehaviorLstmPolicy",
                                 "policy_kwargs": original.policy_kwargs, "dynamics": "classic", "actions": 91,
                                 "observation_size": original.observation_space.shape[0],
                                 "parameters": sum(p.numel() for p in original.policy.parameters())}
    assert record["machine"]["cpu_count"] >= 1 and record["machine"]["torch"] == th.__version__
    curve = record["curve"]
    assert curve["rows"] == 2 and curve["last_row_evaluated"] and len(curve["last_evaluated"]) == min(2, HELD_OUT_ROWS)
    assert curve["last_row"]["normal_goal"] == pytest.approx(rows[-1]["normal_goal"])
    assert [r["timesteps"] for r in curve["last_evaluated"]] == [r["timesteps"] for r in rows]
    assert "Stable-Baselines3" in record["trained_with"]


def test_the_cli_exports_and_refuses_bad_input_before_writing(run: Path, tmp_path: Path, capsys):
    from cpalgo import cli

    out = tmp_path / "anchor.zip"
    assert cli.main(["export-anchor", str(run), "--out", str(out), "--json", str(tmp_path / "anchor.json")]) == 0
    printed = capsys.readouterr().out
    assert f"{out}:" in printed and "2 segments" in printed and "record written to" in printed
    assert json.loads((tmp_path / "anchor.json").read_text())["anchor"]["path"] == str(out)

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "folder.zip").mkdir()
    (bad / "file").write_text("")
    no_state = bad / "no_state"  # a run folder whose checkpoint is an export
    no_state.mkdir()
    shutil.copy(out, no_state / "checkpoint.zip")
    shutil.copy(run / "run.json", no_state / "run.json")
    broken = bad / "broken"
    broken.mkdir()
    (broken / "checkpoint.zip").write_text("not a zip")
    shutil.copy(run / "run.json", broken / "run.json")
    target = str(bad / "x.zip")
    for argv, message in (
            ([str(bad / "nothing"), "--out", target], "RUN_DIR: no such folder"),
            ([str(bad), "--out", target], "RUN_DIR: '" + str(bad) + "' holds no checkpoint.zip and no run.json"),
            ([str(no_state), "--out", target], "holds no resume state"),
            ([str(broken), "--out", target], "does not load as a CounterPlay checkpoint"),
            ([str(run), "--out", str(bad / "folder.zip")], "--out: '" + str(bad / "folder.zip") + "' is a folder"),
            ([str(run), "--out", str(bad / "file" / "x.zip")], "--out: '" + str(bad / "file") + "' is a file"),
            ([str(run), "--out", str(bad / "x.pt")], "--out: '" + str(bad / "x.pt") + "' must end in .zip"),
            ([str(run), "--out", str(run / "checkpoint.zip")], "is the run's own checkpoint"),
            ([str(run), "--out", target, "--json", str(bad)], "--json: '" + str(bad) + "' is a folder"),
            ([str(run), "--out", target, "--json", target], "--json: '" + target + "' is the same file as the exported anchor")):
        before = sorted(p.name for p in bad.rglob("*"))
        with pytest.raises(SystemExit) as exc:
            cli.main(["export-anchor", *argv])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and "error: " in err and message in err, (argv, err)
        assert sorted(p.name for p in bad.rglob("*")) == before  # nothing written, no temp file left
    assert not list(run.glob(".*"))  # no temp file in the run folder either
