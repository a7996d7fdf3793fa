"""The evaluator's simulator takes the dynamics model of the learned policies it is given
(their action sets: 12 jerk, 91 classic): a classic policy evaluates, mixed dynamics are
refused naming the argument, the BC model converts, the jerk PPO co-player falls back."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("cpsim.simulator")

from cpalgo.evaluate import runner as R  # noqa: E402
from cpsim.config import num_actions  # noqa: E402

TINY = dict(lstm_hidden_size=8, features_extractor_kwargs=dict(ego_width=8, condition_width=8, partner_width=8,
                                                               road_width=8, features_dim=8))


@pytest.fixture(scope="module")
def two():
    """Two tasks: one of each split."""
    tasks = R.make_tasks("procedural", "both", 1, seed=0)
    assert {t.split for t in tasks} == {"interactive", "random"}
    return tasks


@pytest.fixture(scope="module")
def ckpts(two, tmp_path_factory):
    """A tiny untrained classic-dynamics CounterPlay (BehaviorLstmPolicy) and a tiny jerk
    RecurrentPPO, both saved."""
    from sb3_contrib import RecurrentPPO

    from cpalgo import CounterPlay
    from cpsim import SelfPlayVecEnv

    folder = tmp_path_factory.mktemp("dyn")
    env = SelfPlayVecEnv([two[0].scenario], num_worlds=1, max_agents=4, seed=0, dynamics="classic")
    assert env.action_space.n == num_actions("classic")
    classic = CounterPlay("BehaviorLstmPolicy", env, counterfactual=False, n_steps=8, batch_size=32, n_epochs=1,
                          seed=0, policy_kwargs=TINY)
    classic.save(folder / "classic.zip")
    env.close()
    env = SelfPlayVecEnv([two[0].scenario], num_worlds=1, max_agents=4, seed=0)
    assert env.action_space.n == num_actions("jerk")
    jerk = RecurrentPPO("MlpLstmPolicy", env, n_steps=8, seed=0, policy_kwargs=dict(lstm_hidden_size=8, net_arch=[8]))
    jerk.save(folder / "jerk.zip")
    env.close()
    return {"classic": str(folder / "classic.zip"), "jerk": str(folder / "jerk.zip")}


def _finite(columns):
    for k in ("score", "comfort", "lane_align", "lane_center"):
        assert np.all(np.isfinite(columns[k])), k
    assert np.all((columns["steps_alive"] >= 1) & (columns["steps_alive"] <= 91))


def test_policy_dynamics_reads_the_action_set(ckpts):
    assert R.policy_dynamics(ckpts["classic"]) == "classic"
    assert R.policy_dynamics(ckpts["jerk"]) == "jerk"
    assert R.policy_dynamics(R.load_model(ckpts["classic"])) == "classic"
    for builtin in ("expert", "idm", "tracking", "reactive"):
        assert R.policy_dynamics(R.as_ego_policy(builtin)) is None
    assert R.policy_dynamics(lambda obs: np.zeros(len(obs))) is None


def test_classic_policy_evaluates_in_classic_dynamics(two, ckpts):
    regimes = ["idm", "bc", "replay", "normal", "mix"]
    ev = R.Evaluator(two, regimes, traffic_policy=ckpts["classic"], policies=[ckpts["classic"]],
                     config=R.EvalConfig(progress=False, max_worlds=16))
    assert ev.dynamics == "classic" and ev.sim.config.dynamics == "classic"
    assert ev.sim.config.goal_criterion == "evaluation"
    res = ev.run(ckpts["classic"], label="classic")
    c = res.columns
    assert res.num_rows == len(two) * len(regimes) and set(c["regime"]) == set(regimes)
    assert res.meta["dynamics"] == "classic"
    _finite(c)
    # the built-in controllers and the teachers drive under classic dynamics too
    for name in ("expert", "idm", "tracking", "reactive"):
        other = ev.run(name).columns
        _finite(other)
        if name == "expert":  # log replay of tasks whose log reaches the goal: completes
            rep = other["regime"] == "replay"
            assert other["goal"][rep].all() and not other["at_fault_collision"][rep].any()
    # the traffic policy alone also decides (no ego given up front)
    assert R.Evaluator(two, ["normal"], traffic_policy=ckpts["classic"],
                       config=R.EvalConfig(progress=False)).dynamics == "classic"
    # and the convenience function picks it from the ego
    r = R.evaluate(ckpts["classic"], two[:1], ["idm"], progress=False)
    assert r.meta["dynamics"] == "classic"


def test_mixed_dynamics_are_refused_naming_the_argument(two, ckpts, monkeypatch):
    cfg = R.EvalConfig(progress=False)
    with pytest.raises(ValueError, match=r"policy '.*classic\.zip': acts in classic dynamics .* jerk dynamics"):
        R.evaluate_checkpoints([ckpts["jerk"], ckpts["classic"]], two, ["idm"], progress=False)
    with pytest.raises(ValueError, match=r"traffic_policy: acts in jerk dynamics .*classic dynamics"):
        R.Evaluator(two, ["normal"], traffic_policy=ckpts["jerk"], policies=[ckpts["classic"]], config=cfg)
    with pytest.raises(ValueError, match=r"ppo_policy: acts in jerk dynamics .*classic dynamics"):
        R.Evaluator(two, ["selfplay"], traffic_policy=ckpts["classic"], ppo_policy=ckpts["jerk"], config=cfg)
    # an explicit choice (dynamics= or sim_config) must agree with the policies
    with pytest.raises(ValueError, match=r"classic dynamics .* dynamics gives jerk"):
        R.Evaluator(two, ["idm"], policies=[ckpts["classic"]], dynamics="jerk", config=cfg)
    with pytest.raises(ValueError, match=r"sim_config.dynamics gives classic"):
        R.Evaluator(two, ["idm"], policies=[ckpts["jerk"]], sim_config={"dynamics": "classic"}, config=cfg)
    # an evaluator built for jerk refuses a classic ego before any step
    ev = R.Evaluator(two, ["idm"], config=cfg)
    assert ev.dynamics == "jerk"
    with pytest.raises(ValueError, match=r"acts in classic dynamics .* jerk dynamics"):
        ev.run(ckpts["classic"])
    # the default co-player policy must act in the evaluation's dynamics
    monkeypatch.setattr(R, "DEFAULT_TRAFFIC_PATHS", {"classic": R.Path(ckpts["jerk"])})  # a mis-shipped default
    with pytest.raises(ValueError, match=r"traffic_policy: .*default jerk\.zip acts in jerk"):
        R.Evaluator(two, ["normal"], policies=[ckpts["classic"]], config=cfg)


def test_cli_messages_and_classic_run(ckpts, tmp_path, capsys):
    from cpalgo.evaluate.__main__ import main

    base = ["--regimes", "idm,normal", "--n", "1", "--no-progress", "--no-plots"]
    out = tmp_path / "res"
    cases = ((["--policy", ckpts["classic"], "--traffic-policy", ckpts["jerk"]], "--traffic-policy: acts in jerk"),
             (["--policy", ckpts["jerk"], "--policy", ckpts["classic"]], "--policy '" + ckpts["classic"]),
             (["--policy", ckpts["classic"], "--dynamics", "jerk"], "but --dynamics gives jerk"),
             (["--policy", ckpts["classic"], "--regimes", "selfplay", "--ppo-policy", ckpts["jerk"]],
              "--ppo-policy: acts in jerk"))
    for extra, message in cases:
        assert main(base + extra + ["--out", str(out)]) == 2  # the last --regimes counts
        err = capsys.readouterr().err
        assert message in err and "classic" in err and "jerk" in err, err
        assert not out.exists()
    # a classic ego and traffic policy run end to end; the summary records the dynamics
    assert main(["--policy", f"c={ckpts['classic']}", "--traffic-policy", ckpts["classic"], *base,
                 "--dynamics", "classic", "--out", str(out)]) == 0
    run = json.loads((out / "summary.json").read_text())["run"]
    assert run["dynamics"] == "classic" and run["policies"][0]["dynamics"] == "classic"


def test_bc_model_follows_the_simulator_dynamics(two, ckpts, tmp_path):
    import torch as th

    from cpalgo.traffic.bc import BCPolicy, targets_to_logits
    from cpsim import SelfPlayVecEnv

    env = SelfPlayVecEnv([two[0].scenario], num_worlds=1, max_agents=4, seed=0)
    lay = env.obs_layout
    env.close()
    cond = (lay.condition.start, lay.condition.stop)
    targets = BCPolicy(lay.size, num_actions("jerk"), (8,), cond, head="targets")
    path = targets.save(tmp_path / "targets.pt")
    cfg = R.EvalConfig(progress=False)
    ev = R.Evaluator(two, ["bc"], bc_policy=path, policies=[ckpts["classic"]], config=cfg)
    bc = ev.bc_policy
    assert ev.dynamics == "classic" and bc.dynamics == "classic" and bc.num_actions == num_actions("classic")
    obs = th.as_tensor(np.random.default_rng(0).normal(size=(64, lay.size)).astype(np.float32))
    want = targets_to_logits(bc.raw(obs) * th.as_tensor((5.0, 4.0)), obs, "classic").argmax(-1).numpy()
    got = bc.predict(obs.numpy())[0]
    np.testing.assert_array_equal(got, want)
    assert got.max() < num_actions("classic") and got.max() >= num_actions("jerk")  # classic's larger set
    _finite(ev.run("expert").columns)
    # the model object given is not changed (a jerk evaluation still gets jerk actions)
    assert targets.dynamics == "jerk"
    assert R.Evaluator(two, ["bc"], bc_policy=targets, config=cfg).bc_policy is targets
    # a BC model as the ego converts the same way
    _finite(ev.run(path, label="bc-ego").columns)
    # an 'actions' head is one dynamics' action set: refused under the other
    actions = BCPolicy(lay.size, num_actions("jerk"), (8,), cond).save(tmp_path / "actions.pt")
    with pytest.raises(ValueError, match=r"bc_policy: the BC model has an 'actions' head over 12 actions"):
        R.Evaluator(two, ["bc"], bc_policy=actions, policies=[ckpts["classic"]], config=cfg)
    classic_actions = BCPolicy(lay.size, num_actions("classic"), (8,), cond, dynamics="classic")
    assert R.Evaluator(two, ["bc"], bc_policy=classic_actions, policies=[ckpts["classic"]],
                       config=cfg).bc_policy is classic_actions


def test_jerk_ppo_coplayer_falls_back_under_classic(two, ckpts, tmp_path, capsys, monkeypatch):
    import cpsim

    monkeypatch.setattr(R, "DEFAULT_PPO_PATHS", {"classic": R.Path(ckpts["jerk"]), "jerk": R.Path(ckpts["jerk"])})
    cfg = R.EvalConfig(progress=False)
    traffic = R.load_model(ckpts["classic"])
    ev = R.Evaluator(two, ["selfplay"], traffic_policy=traffic, config=cfg)
    assert ev.dynamics == "classic" and ev.ppo_policy is None
    sp = ev._drivers["selfplay"]
    assert sp.model is traffic and sp.condition is None  # the traffic policy under p_train conditions
    assert "jerk.zip" in ev.notes["selfplay"] and "p_train" in ev.notes["selfplay"]
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "p_train" in warnings[0]
    res = ev.run(traffic, label="classic")
    _finite(res.columns)
    assert res.meta["notes"]["selfplay"] == ev.notes["selfplay"]
    # under jerk dynamics the (jerk) default PPO policy is used, under the normal profile
    jerk = R.Evaluator(two, ["selfplay"], traffic_policy=ckpts["jerk"], config=cfg)
    assert jerk.ppo_policy is not None and not jerk.notes
    assert np.array_equal(jerk._drivers["selfplay"].condition, cpsim.profile("normal"))
    # with no learned policy given, the default co-player decides (here a classic one)
    monkeypatch.setattr(R, "DEFAULT_TRAFFIC_PATHS", {"classic": R.Path(ckpts["classic"])})
    ev = R.Evaluator(two, ["selfplay", "normal"], config=cfg)
    assert ev.dynamics == "classic" and ev.ppo_policy is None and "selfplay" in ev.notes
    assert "classic.zip" in ev.dynamics_source
    _finite(ev.run("expert").columns)
    capsys.readouterr()
    # the command line says so in the summary
    from cpalgo.evaluate.__main__ import main

    out = tmp_path / "res"
    assert main(["--policy", ckpts["classic"], "--traffic-policy", ckpts["classic"], "--regimes", "selfplay",
                 "--n", "1", "--no-progress", "--no-plots", "--out", str(out)]) == 0
    run = json.loads((out / "summary.json").read_text())["run"]
    assert run["dynamics"] == "classic" and run["ppo_policy"] is None and "p_train" in run["notes"]["selfplay"]
    assert sum(line.startswith("warning:") for line in capsys.readouterr().err.splitlines()) == 1


def test_default_coplayers_follow_the_dynamics(two, ckpts, tmp_path, capsys, monkeypatch):
    """Without a co-player given, each dynamics gets its own shipped anchor as traffic and
    its own PPO co-player; without one the selfplay regime falls back, with a note."""
    cfg = R.EvalConfig(progress=False)
    classic = R.Evaluator(two, ["normal", "selfplay"], policies=[ckpts["classic"]], config=cfg)
    assert classic.default_paths["traffic_policy"].name == "anchor.zip"
    assert R.policy_dynamics(classic.traffic_policy, "traffic_policy") == "classic"
    assert classic.default_paths["ppo_policy"].name == "ppo_traffic_classic.zip" and not classic.notes
    assert R.policy_dynamics(classic.ppo_policy, "ppo_policy") == "classic"
    jerk = R.Evaluator(two, ["normal", "selfplay"], policies=[ckpts["jerk"]], config=cfg)
    assert jerk.default_paths["traffic_policy"].name == "anchor_imitation.zip"
    assert jerk.default_paths["ppo_policy"].name == "ppo_traffic.zip" and not jerk.notes
    # nothing learned given: the self-play anchor decides the dynamics, whichever regimes
    assert R.Evaluator(two, ["normal"], config=cfg).dynamics == "classic"
    only_ppo = R.Evaluator(two, ["selfplay", "idm"], config=cfg)
    assert only_ppo.dynamics == "classic" and "anchor.zip" in only_ppo.dynamics_source
    monkeypatch.setitem(R.DEFAULT_PPO_PATHS, "classic", tmp_path / "none.zip")
    classic = R.Evaluator(two, ["selfplay"], policies=[ckpts["classic"]], config=cfg)
    assert classic.ppo_policy is None and "no PPO co-player ships" in classic.notes["selfplay"]
    assert classic.default_paths["traffic_policy"].name == "anchor.zip"
    capsys.readouterr()
    # the command line records the files it took
    from cpalgo.evaluate.__main__ import main

    out = tmp_path / "res"
    assert main(["--policy", ckpts["jerk"], "--regimes", "selfplay,normal", "--n", "1", "--no-progress",
                 "--no-plots", "--out", str(out)]) == 0
    run = json.loads((out / "summary.json").read_text())["run"]
    assert run["ppo_policy"].endswith("ppo_traffic.zip") and run["traffic_policy"].endswith("anchor_imitation.zip")


def test_held_out_outcomes_use_the_model_dynamics(ckpts):
    from cpalgo.evaluate.held_out import held_out_outcomes

    rates = held_out_outcomes(R.load_model(ckpts["classic"]), 1, 4)
    assert rates.tasks == 1 and rates.agents >= 1
