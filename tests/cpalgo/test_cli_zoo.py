"""The `counterplay` command, the zoo recipes, the rl-zoo3 launcher and atomic checkpoints."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from cpalgo import cli, zoo
from cpalgo.checkpoint import AtomicCheckpointCallback, save_model_atomic
from cpalgo.recipes import SELFPLAY_ENV_ID, ZOO_DIR, load_recipe, resolve_path, shipped_names, shipped_path

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def tiny_recipe(tmp_path: Path, source: Path, **extra) -> Path:
    """A copy of a shipped recipe shrunk to seconds of work."""
    doc = yaml.safe_load(source.read_text())
    entry = doc[SELFPLAY_ENV_ID]
    entry.update(n_envs=16, n_steps=8, batch_size=64, n_epochs=1, n_timesteps=256)
    entry["env_kwargs"].update(max_agents=8, num_scenarios=2)
    entry.update(extra)
    out = tmp_path / source.name
    out.write_text(yaml.safe_dump(doc))
    return out


def test_shipped_recipes_parse():
    anchor = load_recipe(ZOO_DIR / "anchor.yml")
    post = load_recipe(ZOO_DIR / "counterplay.yml")
    assert anchor.policy == post.policy == "MlpLstmPolicy"
    # post-training must build the same network as the anchor it starts from
    assert anchor.algo_kwargs["policy_kwargs"] == post.algo_kwargs["policy_kwargs"]
    assert post.algo_kwargs["window"] == (5, 60) and post.algo_kwargs["rho"] == 0.5
    assert anchor.num_worlds * anchor.env_kwargs["max_agents"] == anchor.n_envs
    assert "vec_env_wrapper" not in anchor.algo_kwargs and "env_kwargs" not in anchor.algo_kwargs
    # the fine-tuning stage of the shipped anchor: the same recipe at a lower learning rate
    finetune = load_recipe(ZOO_DIR / "anchor_finetune.yml")
    assert finetune.env_kwargs == anchor.env_kwargs and finetune.n_envs == anchor.n_envs
    assert finetune.algo_kwargs["learning_rate"] == 1e-4 < anchor.algo_kwargs["learning_rate"]
    assert finetune.n_timesteps == 150_000
    same = {k: v for k, v in finetune.algo_kwargs.items() if k != "learning_rate"}
    assert same == {k: v for k, v in anchor.algo_kwargs.items() if k != "learning_rate"}


def test_selfplay_post_training_recipe_is_its_anchors_setup():
    """zoo/counterplay_selfplay.yml post-trains the self-play anchor with its network, env,
    return (gamma, GAE, reward clamp) and PPO sizes, the paper's learning rate and
    zoo/counterplay.yml's CounterPlay settings, so that PPO-Continue continues the anchor's
    own training."""
    anchor = load_recipe(ZOO_DIR / "anchor_selfplay.yml")
    post = load_recipe(ZOO_DIR / "counterplay_selfplay.yml")
    flat = load_recipe(ZOO_DIR / "counterplay.yml")
    assert post.policy == anchor.policy == "BehaviorLstmPolicy"
    assert post.algo_kwargs["policy_kwargs"] == anchor.algo_kwargs["policy_kwargs"]
    ppo = ("gamma", "gae_lambda", "clip_reward", "n_epochs", "batch_size", "vf_coef", "max_grad_norm",
           "normalize_advantage", "clip_range")
    for key in ppo:
        assert post.algo_kwargs[key] == anchor.algo_kwargs[key], key
    assert post.algo_kwargs["ent_coef"] == 0.005   # the anchor run's entropy weight from 55M on
    for key in ("dynamics", "max_agents", "condition"):
        assert post.env_kwargs[key] == anchor.env_kwargs[key], key
    assert post.algo_kwargs["learning_rate"] == flat.algo_kwargs["learning_rate"]  # cosine(3e-5)
    same = {k: v for k, v in flat.algo_kwargs.items() if k not in (*ppo, "ent_coef", "policy_kwargs")}
    assert {k: post.algo_kwargs[k] for k in same} == same
    assert post.n_envs == flat.n_envs and post.env_kwargs["num_scenarios"] == flat.env_kwargs["num_scenarios"]


def test_classic_ppo_coplayer_recipe_is_the_anchors_without_conditions():
    """zoo/ppo_traffic_classic.yml trains the selfplay regime's co-player apart from the anchor:
    the anchor's dynamics and reward, every agent under the normal profile (unconditioned)."""
    from cpsim.envs.selfplay import SelfPlayVecEnv

    anchor = load_recipe(ZOO_DIR / "anchor_selfplay.yml")
    traffic = load_recipe(ZOO_DIR / "ppo_traffic_classic.yml")
    assert traffic.env_kwargs["dynamics"] == anchor.env_kwargs["dynamics"] == "classic"
    assert anchor.env_kwargs["condition"] == "train" and traffic.env_kwargs["condition"] == "normal"
    assert traffic.algo_kwargs["clip_reward"] == anchor.algo_kwargs["clip_reward"] == 1.0
    env = SelfPlayVecEnv(num_scenarios=1, **traffic.env_kwargs)
    try:
        assert env.fixed_condition is not None  # one condition for every agent
    finally:
        env.close()


@pytest.mark.parametrize("text, match", [
    ("[1, 2", "not valid YAML"),
    ("other-env: {policy: x, n_envs: 1, n_timesteps: 1}", "no entry"),
    (f"{SELFPLAY_ENV_ID}: {{policy: x, n_envs: 1}}", "n_timesteps"),
    (f"{SELFPLAY_ENV_ID}: {{policy: x, n_envs: 1, n_timesteps: 1, policy_kwargs: 'open(1)'}}", "policy_kwargs"),
])
def test_bad_recipes_name_the_problem(tmp_path, text, match):
    path = tmp_path / "bad.yml"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as err:
        load_recipe(path)
    assert "bad.yml" in str(err.value)
    with pytest.raises(ValueError, match="no such file"):
        load_recipe(tmp_path / "missing.yml")


class _Saver:
    """Stands in for an SB3 model: writes its payload, or dies half-way."""

    def __init__(self, payload: bytes, fail: bool = False):
        self.payload, self.fail = payload, fail

    def save(self, path: str) -> None:
        with open(path, "wb") as fh:
            fh.write(self.payload[: len(self.payload) // 2])
            if self.fail:
                raise RuntimeError("crash while saving")
            fh.write(self.payload[len(self.payload) // 2:])


def test_atomic_save_keeps_the_last_good_checkpoint(tmp_path):
    target = tmp_path / "model.zip"
    assert save_model_atomic(_Saver(b"first-good-checkpoint"), target) == target
    with pytest.raises(RuntimeError):
        save_model_atomic(_Saver(b"second-checkpoint-never-finished", fail=True), target)
    assert target.read_bytes() == b"first-good-checkpoint"
    assert target.stat().st_mode & 0o044  # readable by others, as a plain save would be
    assert [p.name for p in tmp_path.iterdir()] == ["model.zip"]  # no temp file left
    assert save_model_atomic(_Saver(b"x"), tmp_path / "noext") == tmp_path / "noext.zip"
    with pytest.raises(ValueError, match="save_freq"):
        AtomicCheckpointCallback(0, target)


def usage_error(capsys, argv: list[str]) -> str:
    """Run the command, expect a usage error (exit status 2); return its stderr."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "error:" in err and "Traceback" not in err
    return err


def test_pool_command_summarises_families(capsys):
    assert cli.main(["pool", "--n", "6", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert "6 scenarios generated" in out
    for family in ("intersection", "merge", "parked"):
        assert family in out
    assert "unknown ['spaghetti']" in usage_error(capsys, ["pool", "--n", "2", "--families", "spaghetti"])


def test_train_anchor_then_post_train_end_to_end(tmp_path, capsys):
    anchor_cfg = tiny_recipe(tmp_path, ZOO_DIR / "anchor.yml")
    post_cfg = tiny_recipe(tmp_path, ZOO_DIR / "counterplay.yml")
    anchor = tmp_path / "anchor.zip"
    assert cli.main(["train-anchor", "--config", str(anchor_cfg), "--out", str(anchor), "--eval-tasks", "2",
                     "--no-progress", "--threads", "1"]) == 0
    report = json.loads((tmp_path / "anchor.json").read_text())
    rates = report["normal_condition_outcomes"]
    assert rates["agents"] > 0
    assert sum(rates[k] for k in ("goal", "collision", "offroad", "timeout")) == pytest.approx(1.0)

    out = tmp_path / "post"
    assert cli.main(["post-train", "--anchor", str(anchor), "--config", str(post_cfg), "--out", str(out),
                     "--timesteps", "256", "--eval-tasks", "2", "--no-progress", "--threads", "1"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timesteps"] >= 256
    assert summary["budget"]["main"] > 0
    assert summary["outcomes_before"]["agents"] == summary["outcomes_after"]["agents"] > 0
    md = (out / "summary.md").read_text()
    assert (out / "counterplay.zip").is_file() and md.startswith("# CounterPlay")
    assert "{" not in md and "| searches |" in md and "| main |" in md  # tables, not raw JSON
    from sb3_contrib import RecurrentPPO

    from cpalgo import CounterPlay
    from cpalgo.evaluate.runner import load_model

    loaded = CounterPlay.load(out / "counterplay.zip", device="cpu")
    assert loaded.num_timesteps == summary["timesteps"]
    # the evaluation loads a CounterPlay checkpoint as CounterPlay, an anchor as RecurrentPPO
    assert type(load_model(out / "counterplay.zip")) is CounterPlay
    assert type(load_model(anchor)) is RecurrentPPO

    err = usage_error(capsys, ["post-train", "--anchor", str(tmp_path / "nope.zip"), "--config", str(post_cfg),
                               "--out", str(out), "--no-progress"])
    assert "--anchor" in err and "nope.zip" in err


def test_train_anchor_imitation_warm_start(tmp_path):
    cfg = tiny_recipe(tmp_path, ZOO_DIR / "anchor.yml")
    out = tmp_path / "imitation.zip"
    assert cli.main(["train-anchor", "--config", str(cfg), "--out", str(out), "--imitate", "1",
                     "--imitate-worlds", "2", "--imitate-epochs", "1", "--imitate-beta", "0.5",
                     "--imitate-only", "--eval-tasks", "2", "--no-progress", "--threads", "1"]) == 0
    report = json.loads((tmp_path / "imitation.json").read_text())
    assert report["timesteps"] == 0  # --imitate-only: no PPO step
    assert [r["round"] for r in report["imitation_rounds"]] == [0]
    assert report["imitation_rounds"][0]["beta"] == 0.5
    assert report["imitation_rounds"][0]["transitions"] > 0
    # the warm-started weights continue with PPO through --init
    cont = tmp_path / "anchor.zip"
    assert cli.main(["train-anchor", "--config", str(cfg), "--init", str(out), "--out", str(cont),
                     "--eval-tasks", "2", "--no-progress", "--threads", "1"]) == 0
    assert json.loads((tmp_path / "anchor.json").read_text())["timesteps"] >= 256
    # weights only: no Adam moments, a smaller file, still loadable
    slim = tmp_path / "slim.zip"
    assert cli.main(["train-anchor", "--config", str(cfg), "--init", str(cont), "--out", str(slim),
                     "--timesteps", "1", "--drop-optimizer-state", "--eval-tasks", "2", "--no-progress",
                     "--threads", "1"]) == 0
    from sb3_contrib import RecurrentPPO

    full, thin = RecurrentPPO.load(cont, device="cpu"), RecurrentPPO.load(slim, device="cpu")
    assert full.policy.optimizer.state_dict()["state"] and not thin.policy.optimizer.state_dict()["state"]
    assert slim.stat().st_size < cont.stat().st_size
    with pytest.raises(SystemExit):
        cli.main(["train-anchor", "--config", str(cfg), "--out", str(out), "--imitate", "-1"])
    with pytest.raises(SystemExit):
        cli.main(["train-anchor", "--config", str(cfg), "--out", str(out), "--imitate", "1", "--imitate-beta", "2"])


def test_train_anchor_with_the_teachers_imitation_term_ships_a_plain_recurrent_ppo(tmp_path):
    """--teacher-coef: the PPO stage is cpalgo.anchor.teacher_ppo.TeacherPPO; the saved anchor is a
    plain sb3-contrib RecurrentPPO with its weights."""
    from sb3_contrib import RecurrentPPO

    cfg = tiny_recipe(tmp_path, ZOO_DIR / "anchor.yml")
    out = tmp_path / "teacher.zip"
    assert cli.main(["train-anchor", "--config", str(cfg), "--out", str(out), "--teacher", "reactive",
                     "--teacher-coef", "0.5", "--teacher-coef-final", "0.1", "--timesteps", "300",
                     "--teacher-style-pairs", "1", "--style-pair-focus",
                     "--eval-tasks", "2", "--no-progress", "--threads", "1"]) == 0
    shipped = RecurrentPPO.load(out, device="cpu")
    assert type(shipped) is RecurrentPPO
    assert shipped.policy.optimizer.state_dict()["state"]  # Adam's moments travel with the export
    assert json.loads((tmp_path / "teacher.json").read_text())["timesteps"] >= 300
    with pytest.raises(SystemExit):
        cli.main(["train-anchor", "--config", str(cfg), "--out", str(out), "--teacher-coef", "-1"])
    for bad in (["--teacher-style-pairs", "1"], ["--teacher-coef", "1", "--style-pair-focus"]):
        with pytest.raises(SystemExit):  # pairs need TeacherPPO, focus needs pairs
            cli.main(["train-anchor", "--config", str(cfg), "--out", str(tmp_path / "bad.zip"), *bad])
        assert not (tmp_path / "bad.zip").exists()


def test_zoo_launcher_trains_counterplay_through_rl_zoo3(tmp_path, monkeypatch, capsys):
    recipe = tiny_recipe(tmp_path, ZOO_DIR / "counterplay.yml")
    monkeypatch.chdir(tmp_path)
    logs = tmp_path / "logs"
    # rl-zoo3's evaluation callback cannot evaluate the batched env: refused when asked for,
    # off by default
    assert zoo.main(["train", "--algo", "counterplay", "--env", SELFPLAY_ENV_ID, "-f", str(recipe),
                     "--log-folder", str(logs), "--eval-freq", "256"]) == 2
    assert "--eval-freq 256" in capsys.readouterr().err and not logs.exists()
    code = zoo.main(["train", "--algo", "counterplay", "--env", SELFPLAY_ENV_ID, "-f", str(recipe),
                     "--log-folder", str(logs), "-n", "128", "--seed", "1", "--eval-freq", "-1"])
    assert code == 0
    code = zoo.main(["train", "--algo", "counterplay", "--env", SELFPLAY_ENV_ID, "-f", str(recipe),
                     "--log-folder", str(logs), "-n", "128", "--seed", "2"])
    assert code == 0 and len(list(logs.glob("counterplay/*/*.zip"))) == 2
    saved_args = [yaml.unsafe_load(p.read_text()) for p in logs.glob("counterplay/*/*/args.yml")]  # an OrderedDict
    assert len(saved_args) == 2 and all(dict(a)["eval_freq"] == -1 for a in saved_args), saved_args
    with pytest.raises(ValueError, match="--eval-freq 512"):  # argparse keeps the last one given
        zoo._no_zoo_evaluation(["--eval-freq", "-1", "--eval-freq=512"])
    saved = list(logs.glob("counterplay/*/*.zip"))
    assert saved, list(logs.rglob("*"))
    from cpalgo import CounterPlay

    model = CounterPlay.load(saved[0], device="cpu")
    assert model.num_timesteps >= 128 and model.n_envs == 16  # 2 worlds x 8 agent slots

    # enjoy on the self-play env reports the agents' episodes (rl-zoo3 alone prints
    # nothing for n_envs > 1)
    capsys.readouterr()
    assert zoo.main(["enjoy", "--algo", "counterplay", "--env", SELFPLAY_ENV_ID, "-f", str(logs),
                     "--n-envs", "16", "-n", "100", "--no-render", "--seed", "0"]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if "agent episodes" in x]
    assert lines, "enjoy printed no episode report"
    assert "goal" in lines[-1] and "mean reward" in lines[-1]


def test_zoo_train_names_a_misspelled_recipe_key_before_rl_zoo3_starts(tmp_path, monkeypatch, capsys):
    """rl-zoo3 hands every key it does not read itself to the algorithm's constructor, which
    fails with a traceback: the launcher checks the keys first and names file, entry and key."""
    import rl_zoo3
    import rl_zoo3.train

    monkeypatch.setattr(rl_zoo3.train, "train", lambda: pytest.fail("rl-zoo3 started"))
    doc = yaml.safe_load((ZOO_DIR / "anchor.yml").read_text())
    entry = doc[SELFPLAY_ENV_ID]
    entry["lerning_rate"] = entry.pop("learning_rate")
    bad = tmp_path / "bad.yml"
    bad.write_text(yaml.safe_dump(doc))
    assert zoo.main(["train", "--algo", "ppo_lstm", "--env", SELFPLAY_ENV_ID, "-f", str(bad), "-n", "8"]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: {SELFPLAY_ENV_ID}: unknown key 'lerning_rate'" in err and "RecurrentPPO" in err
    assert "(did you mean 'learning_rate'?)" in err and "Traceback" not in err

    # a CounterPlay setting is not an argument of RecurrentPPO; -params overrides are checked too
    assert zoo.main(["train", "--algo", "ppo_lstm", "--env", SELFPLAY_ENV_ID, "-f", "zoo/counterplay.yml"]) == 2
    err = capsys.readouterr().err
    assert "unknown keys " in err and "'backtrack'" in err and "'rho'" in err and "'n_steps'" not in err
    assert zoo.main(["train", "--algo", "counterplay", "--env", SELFPLAY_ENV_ID, "-f", "zoo/counterplay.yml",
                     "-params", "rhoo:0.5"]) == 2
    assert "-params: unknown key 'rhoo'" in capsys.readouterr().err
    other = tmp_path / "other.yml"
    other.write_text(yaml.safe_dump({"Other-v0": {"policy": "MlpPolicy"}}))
    assert zoo.main(["train", "--algo", "ppo_lstm", "--env", SELFPLAY_ENV_ID, "-f", str(other)]) == 2
    assert "no entry for env id" in capsys.readouterr().err

    # every shipped recipe passes for the algorithm it is written for
    zoo.register()
    from cpalgo import CounterPlay

    algos = {**rl_zoo3.ALGOS, "counterplay": CounterPlay}
    for name, algo in (("anchor.yml", "ppo_lstm"), ("anchor_finetune.yml", "ppo_lstm"), ("anchor_teacher.yml", "ppo_lstm"),
                       ("ppo_traffic.yml", "ppo_lstm"), ("counterplay.yml", "counterplay"),
                       ("counterplay_fast.yml", "counterplay"), ("counterplay_selfplay.yml", "counterplay")):
        zoo.check_train_recipe(["--algo", algo, "--env", SELFPLAY_ENV_ID, "--conf-file", str(ZOO_DIR / name),
                                "-params", "n_epochs:2"], algos)


def test_selfplay_settings_carrier():
    import gymnasium

    zoo.register()
    env = gymnasium.make(SELFPLAY_ENV_ID, max_agents=4, num_scenarios=1)
    assert env.unwrapped.selfplay_kwargs["max_agents"] == 4
    assert env.action_space.n == 12 and env.observation_space.shape[0] > 0
    with pytest.raises(RuntimeError, match="batched"):
        env.reset()
    assert zoo.SelfPlaySettings(render_mode="human").selfplay_kwargs["render_mode"] == "human"
    assert zoo._translate_config_flag(["-f", "a.yml", "-f2"]) == ["--conf-file", "a.yml", "-f2"]
    assert zoo._translate_config_flag(["-f", "logs/"]) == ["-f", "logs/"]


def test_outcomes_command_evaluates_the_tracking_expert(capsys, tmp_path):
    out = tmp_path / "rates" / "expert.json"
    assert cli.main(["outcomes", "--model", "expert", "--tasks", "6", "--out", str(out)]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-2]
    goal = float(line.split("goal ")[1].split("%")[0])
    assert goal >= 75.0 and "6 tasks" in line  # 95 % on 256 held-out tasks
    written = json.loads(out.read_text())
    assert written["model"] == "expert" and written["tasks"] == 6
    assert written["outcomes"]["goal"] == pytest.approx(goal / 100, abs=1e-3)


@pytest.mark.parametrize("argv, message", [
    (["outcomes", "--condition", "reckless"], "unknown profile 'reckless'"),
    (["post-train", "--config", "missing.yml"], "no such file 'missing.yml'"),
    (["pool", "--n", "2.7"], "expected a whole number, got '2.7'"),
    (["run", "--timesteps", "0"], "must be >= 1"),
    (["run", "--anchor", "nope.zip"], "no such file 'nope.zip'"),
    (["run", "--config", "missing.yml"], "no such file 'missing.yml'"),
    (["outcomes", "--model", "nope.zip", "--tasks", "1"], "does not exist"),
    (["train-anchor", "--init", "nope.zip"], "no such file 'nope.zip'"),
    (["pool", "--seed", "-1", "--n", "2"], "--seed: must be >= 0"),
])
def test_cli_errors_exit_2_without_a_traceback(capsys, argv, message):
    assert message in usage_error(capsys, argv)


def test_run_takes_the_anchor_and_recipe(monkeypatch):
    """``counterplay run --anchor --config``: the main job from another anchor (the self-play one)."""
    import cpalgo.experiments.mainjob as mainjob

    seen = {}

    def fake(**kwargs):
        seen.update(kwargs)
        return {"markdown": "", "wall_s": 0.0}

    monkeypatch.setattr(mainjob, "run_main_job", fake)
    assert cli.main(["run", "--anchor", "zoo/anchor_fast.zip", "--config", "zoo/counterplay_selfplay.yml",
                     "--no-progress"]) == 0
    assert seen["anchor"] == resolve_path("zoo/anchor_fast.zip")
    assert seen["config"] == resolve_path("zoo/counterplay_selfplay.yml")
    assert cli.main(["run", "--no-progress"]) == 0  # the defaults: the self-play anchor and its recipe
    assert seen["anchor"] == resolve_path("zoo/anchor.zip")
    assert seen["config"] == resolve_path("zoo/counterplay_selfplay.yml")


@pytest.mark.parametrize("edit, message", [
    (("  rho: 0.5", "  rhoo: 0.5"), "'rhoo' is not an argument of CounterPlay"),
    (("  rho: 0.5", "  rho: 7.5"), "rho: must lie in [0, 1], got 7.5"),
    (("  n_steps: 96", "  n_steps: 0"), "n_steps: must be a whole number >= 1"),
    (("  batch_size: 4096", "  batch_size: -1"), "batch_size: must be a whole number >= 1"),
    (("    num_scenarios: 192", "    num_scenarios: -3"), "env_kwargs: num_scenarios: must be a whole number >= 1"),
])
def test_post_train_rejects_bad_recipe_values_before_writing_anything(capsys, tmp_path, edit, message):
    recipe = tmp_path / "bad.yml"
    text = Path(resolve_path("zoo/counterplay.yml")).read_text()
    assert edit[0] in text
    recipe.write_text(text.replace(edit[0], edit[1]))
    out = tmp_path / "out"
    error = usage_error(capsys, ["post-train", "--config", str(recipe), "--out", str(out), "--timesteps", "10"])
    assert message in error and str(recipe) in error
    assert not out.exists()


def test_out_paths_below_a_file_fail_up_front(capsys, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for argv in (["outcomes", "--tasks", "1", "--out", str(blocker / "x.json")],
                 ["train-anchor", "--timesteps", "10", "--out", str(blocker / "a.zip")],
                 ["post-train", "--timesteps", "10", "--out", str(blocker)]):
        assert "--out:" in usage_error(capsys, argv)
    assert cli.check_out_path(tmp_path / "new" / "deeper", "--out", folder=True) == tmp_path / "new" / "deeper"


def test_console_script_errors_and_version(tmp_path):
    """The installed command: one error line and exit status 2, never a traceback; --version."""
    import subprocess
    import sys

    def run(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "cpalgo.cli", *argv], cwd=tmp_path, capture_output=True,
                              text=True, timeout=120)

    for argv in (["outcomes", "--condition", "reckless"], ["post-train", "--config", "missing.yml"],
                 ["pool", "--n", "2.7"]):
        done = run(*argv)
        assert done.returncode == 2 and "Traceback" not in done.stderr and "error:" in done.stderr, done.stderr
    version = run("--version")
    assert version.returncode == 0 and version.stdout.strip() == f"counterplay {cli._version()}"
    helped = run("--help")
    assert helped.stdout.count("train-anchor") == 1 and "::" not in helped.stdout  # argparse lists them once


def test_shipped_files_resolve_from_any_folder(tmp_path, monkeypatch):
    """zoo/NAME names the file shipped inside the package when no such file exists here."""
    monkeypatch.chdir(tmp_path)
    assert "anchor.zip" in shipped_names() and "bc_traffic.pt" in shipped_names()
    assert resolve_path("zoo/anchor.zip") == str(shipped_path("anchor.zip")) == resolve_path("zoo/anchor")
    assert load_recipe("zoo/counterplay.yml").path == str(shipped_path("counterplay.yml"))
    assert resolve_path("zoo/nothing.yml") == "zoo/nothing.yml"
    assert zoo._translate_config_flag(["-f", "zoo/counterplay.yml", "-i", "zoo/anchor.zip"]) == [
        "--conf-file", str(shipped_path("counterplay.yml")), "-i", str(shipped_path("anchor.zip"))]
    (tmp_path / "zoo").mkdir()
    (tmp_path / "zoo" / "anchor.zip").write_bytes(b"mine")
    assert resolve_path("zoo/anchor.zip") == "zoo/anchor.zip"  # a file that exists wins
    with pytest.raises(FileNotFoundError, match="shipped"):
        shipped_path("nothing.yml")


def test_recipes_keep_normalize_and_vec_env_wrappers(tmp_path, capsys):
    """The recipe loader keeps rl-zoo3's normalize and vec_env_wrapper; the counterplay
    command applies the wrappers and refuses what it cannot apply (no silent drop)."""
    from stable_baselines3.common.vec_env import VecCheckNan, VecMonitor

    wrapped = tiny_recipe(tmp_path, ZOO_DIR / "anchor.yml", vec_env_wrapper=[
        "stable_baselines3.common.vec_env.VecMonitor",
        {"stable_baselines3.common.vec_env.VecCheckNan": {"raise_exception": True}}])
    recipe = load_recipe(wrapped)
    assert recipe.vec_env_wrappers == (("stable_baselines3.common.vec_env.VecMonitor", {}),
                                       ("stable_baselines3.common.vec_env.VecCheckNan", {"raise_exception": True}))
    env = cli._make_env(recipe, seed=0)
    assert isinstance(env, VecCheckNan) and isinstance(env.venv, VecMonitor) and env.raise_exception
    assert env.num_envs == 16 and env.get_attr("max_agents", [0]) == [8]

    normalized = tiny_recipe(tmp_path, ZOO_DIR / "counterplay.yml", normalize="{'norm_obs': True, 'norm_reward': False}")
    assert load_recipe(normalized).normalize == {"norm_obs": True, "norm_reward": False}
    assert "normalize" in usage_error(capsys, ["post-train", "--config", str(normalized), "--timesteps", "1",
                                                "--eval-tasks", "1", "--no-progress"])
    other = tiny_recipe(tmp_path, ZOO_DIR / "anchor.yml", frame_stack=4)
    assert load_recipe(other).zoo_only == {"frame_stack": 4}
    assert "frame_stack" in usage_error(capsys, ["train-anchor", "--config", str(other), "--timesteps", "1"])
    bad = tiny_recipe(tmp_path, ZOO_DIR / "anchor.yml", vec_env_wrapper="no.such.Wrapper")
    assert "no.such.Wrapper" in usage_error(capsys, ["train-anchor", "--config", str(bad), "--timesteps", "1"])


@pytest.mark.parametrize("name, gap", [("anchor.zip", 0.1), ("anchor_imitation.zip", 0.2), ("anchor_fast.zip", 0.2)])
def test_shipped_anchors_load_fit_the_size_limit_and_follow_their_style(name, gap):
    """Every shipped anchor responds to the style fields of its condition: on the same
    held-out tasks under the evaluation goal criterion, aggressive agents reach their goal
    more often than cautious ones (the self-play anchor's curve: 97 against 77 %; the
    teacher-imitation anchors on 256 tasks: 83 against 27 %)."""
    from cpalgo.evaluate.runner import load_model, policy_dynamics

    path = shipped_path(name)
    assert path.stat().st_size <= 10 * 2**20  # what a shipped checkpoint may weigh
    model = load_model(path, "anchor")
    assert policy_dynamics(model, "anchor") == ("classic" if name == "anchor.zip" else "jerk")
    if name == "anchor_fast.zip":
        assert type(model.policy.features_extractor).__name__ == "LinearEncoder"
    goal = {c: cli._outcomes(model, 12, 8, condition=c).goal for c in ("aggressive", "cautious")}
    assert goal["aggressive"] > goal["cautious"] + gap, goal
