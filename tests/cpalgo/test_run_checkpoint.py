"""A grid run's resumable checkpoint: weights and counters are replaced together, so a kill
at any moment of a save leaves a pair that belongs together (or none)."""

from __future__ import annotations

import json
import zipfile
from types import SimpleNamespace

import pytest

from cpalgo.experiments import runs
from cpalgo.experiments.grid import RunSpec
from cpalgo.experiments.runs import CHECKPOINT_STATE, _readable_checkpoint, read_checkpoint, save_checkpoint


class Killed(BaseException):
    """Stands in for SIGKILL: nothing after it runs (not even ``except Exception``)."""


class FakeModel:
    """What a checkpoint save reads of a model: SB3's ``save`` (a zip with ``data`` and
    ``policy.pth``), the step counter and the budget."""

    def __init__(self, steps: int):
        self.num_timesteps = steps
        self._n_updates = steps // 100
        self.budget = SimpleNamespace(main=steps, factual=0, candidate=steps // 2, verification=0,
                                      generations=steps // 1000)

    def save(self, path) -> None:
        with zipfile.ZipFile(path, "w") as archive:
            archive.writestr("data", json.dumps({"num_timesteps": self.num_timesteps}))
            archive.writestr("policy.pth", f"weights after {self.num_timesteps}".encode())


def _weights(folder) -> bytes:
    with zipfile.ZipFile(folder / "checkpoint.zip") as archive:
        return archive.read("policy.pth")


def test_the_counters_travel_inside_the_zip(tmp_path):
    save_checkpoint(FakeModel(1000), tmp_path, wall_s=12.5)
    with zipfile.ZipFile(tmp_path / "checkpoint.zip") as archive:
        inside = json.loads(archive.read(CHECKPOINT_STATE))
    assert inside["num_timesteps"] == 1000 and inside["budget"]["candidate"] == 500 and inside["wall_s"] == 12.5
    assert json.loads((tmp_path / "checkpoint.json").read_text()) == inside  # the readable copy
    assert read_checkpoint(tmp_path) == inside


@pytest.mark.parametrize("kill_in", ["zip", "json"])
def test_a_kill_during_a_save_leaves_a_matching_pair(tmp_path, monkeypatch, kill_in):
    """Save at 1000 steps, then kill the save at 2000 steps while it writes the zip (before
    its rename) or between the zip's rename and the json's: the checkpoint read back is
    one save's weights with that same save's counters."""
    save_checkpoint(FakeModel(1000), tmp_path)
    if kill_in == "zip":
        real_save = FakeModel.save

        def killed_save(self, path):
            real_save(self, path)
            raise Killed()
        monkeypatch.setattr(FakeModel, "save", killed_save)
    else:
        def killed_write(path, data):
            raise Killed()
        monkeypatch.setattr(runs, "write_bytes_atomic", killed_write)
    with pytest.raises(Killed):
        save_checkpoint(FakeModel(2000), tmp_path)
    state = read_checkpoint(tmp_path)
    expected = 1000 if kill_in == "zip" else 2000
    assert state["num_timesteps"] == expected
    assert _weights(tmp_path) == f"weights after {expected}".encode()
    if kill_in == "json":  # the readable copy is stale, and it is not what resumes
        assert json.loads((tmp_path / "checkpoint.json").read_text())["num_timesteps"] == 1000
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")], "temp files left behind"


def _old_style_save(model: FakeModel, folder) -> None:
    """How checkpoints were written before the counters went inside the zip: two renames."""
    model.save(folder / "checkpoint.zip")
    (folder / "checkpoint.json").write_text(json.dumps(runs.budget_state(model)))


def test_an_older_checkpoint_resumes_only_when_its_two_files_match(tmp_path):
    _old_style_save(FakeModel(1000), tmp_path)
    assert read_checkpoint(tmp_path)["num_timesteps"] == 1000
    # killed between the two renames of the next save: new weights beside old counters
    FakeModel(2000).save(tmp_path / "checkpoint.zip")
    with pytest.raises(ValueError, match="from another save than the weights"):
        read_checkpoint(tmp_path)
    lines: list[str] = []
    assert _readable_checkpoint(tmp_path, RunSpec("ppo-continue", 0), lines.append) is None
    assert "moved aside, starting over" in lines[0]
    assert (tmp_path / "checkpoint.corrupt.zip").is_file() and (tmp_path / "checkpoint.corrupt.json").is_file()
    assert read_checkpoint(tmp_path) is None  # the run starts over


def test_a_zip_without_counters_and_without_its_json_is_not_resumed(tmp_path):
    FakeModel(1000).save(tmp_path / "checkpoint.zip")
    with pytest.raises(ValueError, match="checkpoint.json is missing"):
        read_checkpoint(tmp_path)
    assert _readable_checkpoint(tmp_path, RunSpec("ppo-continue", 0), None) is None
    assert (tmp_path / "checkpoint.corrupt.zip").is_file()
