"""Post-training methods (cpalgo.methods): the registry, each method's distinguishing
mechanism and the equal-budget stop, on tiny settings (2 worlds x 4 slots, LSTM 16)."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from stable_baselines3.common.callbacks import BaseCallback  # noqa: E402

import cpalgo.methods as methods_module  # noqa: E402
from cpalgo.common.policy_utils import actor_logits  # noqa: E402
from cpalgo.counterplay.distill import collate_teachers  # noqa: E402
from cpalgo.methods import build_method, describe_methods, get_method, method_names, register  # noqa: E402
from cpalgo.methods.base import BudgetedCounterPlay, policy_parameters_equal  # noqa: E402
from cpalgo.methods.distill_controls import StyleDistillation, raw_conditions_from_obs  # noqa: E402
from cpalgo.methods.ppo import OpponentPPO, RewindPPO  # noqa: E402
from cpalgo.policies import BehaviorLstmPolicy  # noqa: E402
from cpalgo.policies import MlpLstmPolicy as FusedMlpLstmPolicy  # noqa: E402
from cpalgo.recipes import CosineSchedule  # noqa: E402
from cpsim import SelfPlayVecEnv  # noqa: E402
from cpsim.conditions import PROFILES, STYLE_MASK  # noqa: E402

EPISODE = 40
POLICY = dict(lstm_hidden_size=16, enable_critic_lstm=False, net_arch=[32])
ALGO = dict(n_steps=EPISODE, batch_size=64, n_epochs=1, policy_kwargs=POLICY)

ISSUE_METHODS = [
    "ppo-continue", "ppo-rewind", "ppo-opponent", "counterplay", "cp-fixed-10", "cp-fixed-30", "cp-fixed-50",
    "cp-no-style", "cp-select-reward", "cp-no-verify", "cp-ppo-recoveries", "cp-only-cautious",
    "cp-only-cautious-normal", "cp-only-normal", "cp-only-normal-aggressive", "cp-only-aggressive",
    "distill-aggressive", "distill-cautious",
]


pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py


def make_env(seed: int = 0) -> SelfPlayVecEnv:
    return SelfPlayVecEnv(num_worlds=2, max_agents=4, num_scenarios=4, seed=seed, episode_steps=EPISODE)


@pytest.fixture(scope="module")
def anchor(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("anchor") / "anchor.zip"
    BudgetedCounterPlay("MlpLstmPolicy", make_env(), counterfactual=False, seed=0, **ALGO).save(path)
    return str(path)


def start_rollout(model, callback=None):
    _, cb = model._setup_learn(10**9, callback)
    cb.on_training_start(locals(), globals())
    return cb


# ----------------------------------------------------------------------------- registry
def test_registry_lists_every_method_of_the_issue_one_line_each():
    names = method_names()
    assert set(ISSUE_METHODS) <= set(names)
    lines = describe_methods().splitlines()
    assert len(lines) == len(names)
    assert all(line.split()[0] in names for line in lines)
    # the settings that make each ablation what it is
    assert get_method("cp-fixed-30").settings == {"backtrack": "fixed", "fixed_depth": 30}
    assert get_method("cp-fixed-70").settings == {"backtrack": "fixed", "fixed_depth": 70}
    assert get_method("cp-fixed-70").group == "ablation"
    assert get_method("cp-only-aggressive").settings["panel"] == ("aggressive",) * 5
    assert get_method("cp-only-aggressive").settings["shared_randomness"] is False
    assert get_method("cp-no-style").settings == {"style_change": False}
    assert get_method("ppo-continue").settings == {"counterfactual": False}
    with pytest.raises(ValueError, match="method: unknown method 'nope'"):
        get_method("nope")


def test_registering_a_method_is_one_line_and_checked():
    spec = register("test-ppo-fast", "PPO-Continue with one epoch (test)", BudgetedCounterPlay,
                    counterfactual=False, n_epochs=1)
    try:
        assert "test-ppo-fast" in method_names()
        assert spec.resolve() is BudgetedCounterPlay
        with pytest.raises(ValueError, match="already registered"):
            register("test-ppo-fast", "again", BudgetedCounterPlay)
        with pytest.raises(ValueError, match="group"):
            register("test-other", "x", BudgetedCounterPlay, group="nonsense")
        with pytest.raises(ValueError, match="summary"):
            register("test-other", "two\nlines", BudgetedCounterPlay)
    finally:
        methods_module._REGISTRY.pop("test-ppo-fast", None)


def test_build_method_finds_the_shipped_anchor_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no zoo/ here: zoo/NAME names the file shipped in the package
    env = SelfPlayVecEnv(num_worlds=1, max_agents=2, num_scenarios=1, dynamics="classic")
    model = build_method("ppo-continue", "zoo/anchor.zip", env, algo_kwargs={"n_steps": 8, "batch_size": 8})
    assert type(model.policy) is BehaviorLstmPolicy and model.action_space.n == 91  # the self-play anchor
    jerk = SelfPlayVecEnv(num_worlds=1, max_agents=2, num_scenarios=1)
    model = build_method("ppo-continue", "zoo/anchor_imitation.zip", jerk, algo_kwargs={"n_steps": 8, "batch_size": 8})
    assert model.policy.lstm_actor.hidden_size == 128  # the anchor's network, weights loaded
    # saved as sb3-contrib's class, built as its fused subclass (the same network, faster)
    assert type(model.policy) is FusedMlpLstmPolicy


def test_build_method_rejects_bad_input(anchor, tmp_path):
    env = make_env()  # every check fails before the env is used, so one env serves them all
    with pytest.raises(ValueError, match="settings: unknown setting 'opponent_fractoin'"):
        build_method("ppo-opponent", anchor, env, algo_kwargs=ALGO, settings={"opponent_fractoin": 0.5})
    with pytest.raises(ValueError, match="anchor: no such checkpoint"):
        build_method("ppo-continue", tmp_path / "missing.zip", env, algo_kwargs=ALGO)
    with pytest.raises(ValueError, match="budget: must be > 0"):
        build_method("ppo-continue", anchor, env, algo_kwargs=ALGO, budget=0)
    classic = SelfPlayVecEnv(num_worlds=2, max_agents=4, num_scenarios=4, episode_steps=EPISODE, dynamics="classic")
    with pytest.raises(ValueError, match="anchor: .* does not fit the network"):  # 91 actions, the anchor 12
        build_method("ppo-continue", anchor, classic, algo_kwargs=ALGO)
    with pytest.raises(ValueError, match="rewind_depth"):
        RewindPPO("MlpLstmPolicy", env, rewind_depth=0, **ALGO)
    with pytest.raises(ValueError, match="opponent_fraction"):
        OpponentPPO("MlpLstmPolicy", env, opponent_fraction=1.0, **ALGO)
    with pytest.raises(ValueError, match="teacher_style"):
        StyleDistillation("MlpLstmPolicy", env, teacher_style="reckless", **ALGO)


def test_build_method_builds_the_anchors_network_not_the_recipes(anchor, tmp_path, capsys):
    """A recipe whose ``policy`` / ``policy_kwargs`` differ from the anchor's gets the anchor's
    network, with one warning line: a flat recipe with a BehaviorLstmPolicy anchor, and a
    difference that no weight shape shows (the activation) with a flat anchor."""
    behavior = tmp_path / "behavior.zip"
    small = dict(lstm_hidden_size=8, features_extractor_kwargs=dict(features_dim=16))
    saved = BudgetedCounterPlay("BehaviorLstmPolicy", make_env(), counterfactual=False, seed=0, n_steps=EPISODE,
                                batch_size=64, n_epochs=1, policy_kwargs=small)
    saved.save(behavior)
    model = build_method("ppo-continue", behavior, make_env(), algo_kwargs=ALGO)  # the recipe: flat MlpLstmPolicy
    assert type(model.policy) is BehaviorLstmPolicy and model.policy.lstm_actor.hidden_size == 8
    assert all(th.equal(a, b) for a, b in zip(model.policy.state_dict().values(), saved.policy.state_dict().values()))
    err = capsys.readouterr().err
    assert err.count("warning:") == 1 and "not policy MlpLstmPolicy (the anchor's: BehaviorLstmPolicy)" in err
    relu = dict(ALGO, policy_kwargs=dict(POLICY, activation_fn=th.nn.ReLU))
    model = build_method("ppo-continue", anchor, make_env(), algo_kwargs=relu)
    assert model.policy.activation_fn is th.nn.Tanh  # the anchor's (sb3-contrib's default)
    assert "activation_fn" in capsys.readouterr().err
    build_method("ppo-continue", anchor, make_env(), algo_kwargs=ALGO)  # the same network: no warning
    assert "warning" not in capsys.readouterr().err


# ----------------------------------------------------------------------------- PPO-Rewind
class AfterStep(BaseCallback):
    """State of every world after each env.step (index -1: at the rollout's start)."""

    def __init__(self) -> None:
        super().__init__()
        self.after: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def _grab(self, key: int) -> None:
        sim = self.training_env.sim
        self.after[key] = (sim.step_count.cpu().numpy().copy(), sim.xy.cpu().numpy().copy())

    def _on_rollout_start(self) -> None:
        self._grab(-1)

    def _on_step(self) -> bool:
        self._grab(self.n_calls - 1)
        return True


def test_rewind_restores_the_world_eight_decisions_before_the_failure(anchor):
    model = build_method("ppo-rewind", anchor, make_env(seed=3), algo_kwargs=ALGO, seed=3)
    rec = AfterStep()
    cb = start_rollout(model, rec)
    assert model.collect_rollouts(model.env, cb, model.rollout_buffer, n_rollout_steps=EPISODE)
    buf = model.rollout_buffer
    checked = 0
    for entry in model.rewind_log:
        assert entry["restored_step"] == max(entry["failure_step"] - 8, 0)
        assert entry["step_count"] == entry["restored_step"]
        decision = entry["decision"]  # the decision taken right after the restore
        back = entry["failure_step"] - entry["restored_step"]
        original = decision - 1 - back  # the decision taken from the restored state the first time
        if original - 1 < -1 or decision >= EPISODE:
            continue
        steps, xy = rec.after[original - 1]
        w = entry["world"]
        assert steps[w] == entry["restored_step"]
        np.testing.assert_array_equal(xy[w], entry["xy"])  # the same world state, bit for bit
        # and the continuation runs on from there
        assert rec.after[decision][0][w] == entry["restored_step"] + 1
        slots = np.arange(w * 4, (w + 1) * 4)
        assert np.all(buf.boundary[decision, slots] == 1.0)
        assert np.all(buf.episode_starts[decision, slots] == 0.0)
        # the memory the restored decision used is the one the original decision used
        keep = (1.0 - buf.episode_starts[original, slots])[None, :, None]
        np.testing.assert_allclose(buf.hidden_states_pi[decision][:, slots],
                                   buf.hidden_states_pi[original][:, slots] * keep, atol=1e-6)
        # the restored agents are live PPO data
        assert buf.active[decision, slots].sum() > 0
        checked += 1
    assert checked >= 1, f"no rewind inside the rollout to check: {model.rewind_log}"
    assert model.rewind_totals["rewinds"] == len(model.rewind_log)


def test_rewind_continuations_count_and_train(anchor):
    model = build_method("ppo-rewind", anchor, make_env(seed=1), algo_kwargs=ALGO, seed=1)
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    model.learn(800)
    assert model.budget.total >= 800
    assert model.rewind_totals["rewinds"] >= 1
    assert 0 < model.rewind_totals["rewound_transitions"] < model.budget.main
    assert any(not th.equal(before[k], v) for k, v in model.policy.state_dict().items())


# ----------------------------------------------------------------------------- PPO-Opponent
def _force_action(policy, action: int) -> None:
    with th.no_grad():
        policy.action_net.weight.zero_()
        policy.action_net.bias.fill_(-30.0)
        policy.action_net.bias[action] = 30.0


def test_opponent_slots_use_the_older_weights(anchor):
    model = build_method("ppo-opponent", anchor, make_env(seed=2), algo_kwargs=ALGO, seed=2,
                         settings={"opponent_fraction": 0.5})
    pool = model.opponent_policies
    assert len(pool) == 1 and policy_parameters_equal(pool[0], model.policy)  # the anchor at the start
    _force_action(pool[0], 3)  # the older checkpoint always takes action 3
    _force_action(model.policy, 7)  # the policy under training action 7
    cb = start_rollout(model)
    assert model.collect_rollouts(model.env, cb, model.rollout_buffer, n_rollout_steps=EPISODE)
    buf = model.rollout_buffer
    trace = np.stack(model._opp.trace)  # (steps, slots): live opponent agents
    actions = buf.actions[..., 0]
    learners = buf.active > 0
    assert trace.sum() > 0 and learners.sum() > 0
    assert np.all(actions[trace] == 3)
    assert np.all(actions[learners] == 7)
    assert not np.any(trace & learners)  # opponent slots never reach PPO
    share = trace.sum() / (trace.sum() + learners.sum())
    assert 0.2 < share < 0.8
    assert model.budget.main == int(trace.sum() + learners.sum())  # every agent transition counts
    # after the second update the pool holds the weights the second rollout was collected with
    model.train()
    collected = {k: v.clone() for k, v in model.policy.state_dict().items()}
    model.collect_rollouts(model.env, cb, model.rollout_buffer, n_rollout_steps=EPISODE)
    model.train()
    assert len(model.opponent_policies) == 2
    newest = model.opponent_policies[-1].state_dict()
    assert all(th.equal(collected[k], newest[k]) for k in collected)
    assert not policy_parameters_equal(model.opponent_policies[-1], model.policy)


# ----------------------------------------------------------------------------- distillation controls
def test_distillation_controls_imitate_the_anchors_styled_probabilities(anchor):
    model = build_method("distill-aggressive", anchor, make_env(seed=4), algo_kwargs=ALGO, seed=4)
    teacher = model.teacher_policy
    assert policy_parameters_equal(teacher, model.policy)
    with th.no_grad():  # the policy under training moves away from the frozen anchor
        for p in model.policy.parameters():
            p.add_(0.05 * th.randn_like(p))
    cb = start_rollout(model)
    assert model.collect_rollouts(model.env, cb, model.rollout_buffer, n_rollout_steps=EPISODE)
    teachers = model._teachers
    assert 0 < len(teachers) <= model.distill_segments
    layout = model.env.obs_layout
    cautious = StyleDistillation("MlpLstmPolicy", make_env(seed=4), teacher_style="cautious", seed=4, **ALGO)
    for t in teachers[:4]:
        raw = raw_conditions_from_obs(t.obs.cpu().numpy(), layout)
        # the teacher sees the aggressive style and the agent's own task fields
        np.testing.assert_allclose(raw[:, STYLE_MASK], np.broadcast_to(PROFILES["aggressive"][STYLE_MASK],
                                                                       raw[:, STYLE_MASK].shape), rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(raw[0, ~STYLE_MASK], t.condition[~STYLE_MASK], rtol=1e-5)
        state = (t.pi_state[0][:, None].contiguous(), t.pi_state[1][:, None].contiguous())
        starts = th.zeros(t.length)
        with th.no_grad():
            anchor_logits, _ = actor_logits(teacher, t.obs, state, starts)
            student_logits, _ = actor_logits(model.policy, t.obs, state, starts)
        th.testing.assert_close(t.logits, anchor_logits)  # the frozen anchor's probabilities
        assert not th.allclose(t.logits, student_logits, atol=1e-3)  # not the policy under training
        # the cautious control's teacher differs on the same states
        cautious_obs = th.as_tensor(layout.replace_condition(t.obs.numpy(), cautious._teacher_condition(t.condition)))
        with th.no_grad():
            cautious_logits, _ = actor_logits(teacher, cautious_obs, state, starts)
        assert not th.allclose(cautious_logits, anchor_logits, atol=1e-4)
    # the student is trained under the normal deployment input
    batch = collate_teachers(teachers, model._deploy_raw, layout.replace_condition, STYLE_MASK)
    student_raw = raw_conditions_from_obs(batch.student_obs.numpy(), layout)
    real = batch.mask.reshape(-1).numpy() > 0
    np.testing.assert_allclose(student_raw[real][:, STYLE_MASK],
                               np.broadcast_to(PROFILES["normal"][STYLE_MASK], student_raw[real][:, STYLE_MASK].shape),
                               rtol=1e-4, atol=1e-5)
    # the update carries the distillation term and empties the teacher list
    model.train()
    assert model._teachers == []
    assert "counterplay/distill_kl" in model.logger.name_to_value


# ----------------------------------------------------------------------------- equal budget
@pytest.mark.parametrize("name", ["ppo-continue", "counterplay", "ppo-rewind", "ppo-opponent", "distill-cautious"])
def test_every_method_stops_at_the_same_budget(anchor, name):
    budget = 700
    model = build_method(name, anchor, make_env(), algo_kwargs=dict(ALGO, learning_rate=CosineSchedule(3e-4)),
                         seed=0)
    model.learn(budget)
    b = model.budget
    # stopped at the rollout step that reached it: within one step of the live slots
    assert budget <= b.total < budget + model.n_envs
    before_last = sum(g["main"] + g["branch"] for g in b.history[:-1])
    assert before_last < budget
    assert model.num_timesteps == b.total  # SB3's counter is B_post too
    assert model._current_progress_remaining == pytest.approx(max(0.0, 1.0 - b.total / budget))
    # the learning rate annealed over the budget (cosine: 0 at the end)
    assert model.policy.optimizer.param_groups[0]["lr"] < 0.5 * 3e-4
