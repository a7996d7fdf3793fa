"""TeacherPPO: self-play PPO with the teacher's actions as an auxiliary imitation term."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th

pytest.importorskip("cpsim.simulator", reason="the simulator is not available")

from cpalgo.anchor.teacher_ppo import TeacherPPO, export_recurrent_ppo  # noqa: E402
from cpsim import SelfPlayVecEnv  # noqa: E402
from cpsim.expert import make_expert  # noqa: E402
from tests.cpalgo.fakes import minibatch_logits  # noqa: E402

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # tests/conftest.py

POLICY = dict(lstm_hidden_size=16, net_arch=[32])
ALGO = dict(n_steps=16, batch_size=64, n_epochs=2, seed=0, policy_kwargs=POLICY)


def make_env() -> SelfPlayVecEnv:
    return SelfPlayVecEnv(num_worlds=3, max_agents=4, num_scenarios=6, seed=1, episode_steps=30, dynamics="jerk",
                          condition="train")


def make_model(**kw) -> TeacherPPO:
    return TeacherPPO("MlpLstmPolicy", make_env(), **{**ALGO, **kw})


def collect(model) -> None:
    """One rollout as ``learn`` runs it, without the update."""
    _, callback = model._setup_learn(10**9, None)
    callback.on_training_start(locals(), globals())
    assert model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)


def test_the_rollout_stores_the_teachers_action_of_every_live_decision():
    model = make_model()
    sim = model.env.sim
    expected = []
    original = TeacherPPO._policy_step

    def spy(self, env, obs, states, starts):  # the teacher's labels of the state the policy sees
        expected.append((make_expert("reactive", sim).actions().reshape(-1).numpy().copy(),
                         sim.policy_mask.reshape(-1).cpu().numpy().copy()))
        return original(self, env, obs, states, starts)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(TeacherPPO, "_policy_step", spy)
        collect(model)
    stored = model.rollout_buffer.extras["teacher_action"]
    assert len(expected) == model.n_steps
    live_total = 0
    for t, (labels, live) in enumerate(expected):
        np.testing.assert_array_equal(stored[t, live], labels[live].astype(np.float32))
        live_total += int(live.sum())
    assert live_total > 0
    assert len(np.unique(stored[np.stack([e[1] for e in expected])])) > 1  # not one constant label


def test_the_term_is_the_masked_nll_of_the_teachers_action_and_pulls_toward_it():
    model = make_model(teacher_coef=2.0, learning_rate=3e-3, n_epochs=10, ent_coef=0.0)
    collect(model)

    def nll() -> float:
        vals = []
        for data, mask, logits in minibatch_logits(model):
            term = model._minibatch_terms(data, mask, logits)["teacher_nll_loss"] / model.current_teacher_coef()
            target = model.rollout_buffer.sample_extras["teacher_action"].reshape(-1).long()
            ref = -th.log_softmax(logits, -1)[mask].gather(-1, target[mask][:, None]).mean()
            assert abs(float(term) - float(ref)) < 1e-5
            vals.append(float(term))
        return float(np.mean(vals))

    before = nll()
    model.train()
    assert nll() < 0.8 * before


def test_zero_weight_gives_the_parameters_of_plain_masked_ppo():
    from cpalgo.common.hooked_train import HookedPPO

    runs = []
    for cls, kw in ((TeacherPPO, dict(teacher_coef=0.0)), (HookedPPO, {})):
        th.manual_seed(0)
        model = cls("MlpLstmPolicy", make_env(), **ALGO, **kw)
        model.learn(200)
        runs.append([p.detach().clone() for p in model.policy.parameters()])
    assert all(th.equal(a, b) for a, b in zip(*runs))


def test_weight_schedule_settings_and_export():
    model = make_model(teacher_coef=1.0, teacher_coef_final=0.25)
    model._current_progress_remaining = 1.0
    assert model.current_teacher_coef() == pytest.approx(1.0)
    model._current_progress_remaining = 0.0
    assert model.current_teacher_coef() == pytest.approx(0.25)
    model._current_progress_remaining = 0.5
    assert model.current_teacher_coef() == pytest.approx(0.625)
    with pytest.raises(ValueError, match="teacher: unknown teacher 'oracle'"):
        make_model(teacher="oracle")
    with pytest.raises(ValueError, match="teacher_coef"):
        make_model(teacher_coef=-1.0)
    from sb3_contrib import RecurrentPPO

    out = export_recurrent_ppo(model, "MlpLstmPolicy", model.env, **ALGO)
    assert type(out) is RecurrentPPO
    for a, b in zip(model.policy.state_dict().values(), out.policy.state_dict().values()):
        assert th.equal(a, b)


def test_paired_style_labels_are_the_teachers_actions_under_a_swapped_panel_style():
    from cpsim.conditions import PANEL, STYLE_MASK, profile

    model = make_model(style_pairs=2)
    sim = model.env.sim
    checked = []
    original = TeacherPPO._policy_step

    def spy(self, env, obs, states, starts):
        own = sim.conditions.clone()
        out = original(self, env, obs, states, starts)
        assert th.equal(sim.conditions, own)  # the world drives on under its own conditions
        live = sim.policy_mask.reshape(-1).cpu().numpy()
        pos = self.rollout_buffer.pos
        for k in range(2):
            cond = self.rollout_buffer.extras["swap_condition"][pos, :, k]
            labels = self.rollout_buffer.extras["swap_action"][pos, :, k]
            sim.conditions.copy_(th.as_tensor(np.where(live[:, None], cond, own.reshape(len(live), -1)))
                                 .reshape(own.shape))
            expected = make_expert("reactive", sim).actions().reshape(-1).numpy()
            sim.conditions.copy_(own)
            np.testing.assert_array_equal(labels[live], expected[live].astype(np.float32))
            np.testing.assert_allclose(cond[live][:, ~STYLE_MASK], own.reshape(len(live), -1)[live][:, ~STYLE_MASK])
            panel = np.stack([profile(name) for name in PANEL])[:, STYLE_MASK]
            assert (np.abs(cond[live][:, None, STYLE_MASK] - panel[None]).max(-1) < 1e-6).any(-1).all()
            checked.append((labels[live], self.rollout_buffer.extras["teacher_action"][pos, live]))
        return out

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(TeacherPPO, "_policy_step", spy)
        collect(model)
    assert len(checked) == 2 * model.n_steps
    swapped, own_labels = (np.concatenate(x) for x in zip(*checked))
    assert (swapped != own_labels).any()  # the swapped style changes some of the teacher's actions


def test_the_paired_term_is_the_nll_under_the_swapped_condition_and_pulls_toward_it():
    model = make_model(teacher_coef=1.0, style_pairs=1, style_pair_coef=3.0, learning_rate=3e-3, n_epochs=10,
                       ent_coef=0.0)
    collect(model)
    layout = model.env.sim.obs_layout

    def pair_nll() -> float:
        vals = []
        for data, mask, logits in minibatch_logits(model):
            terms = model._minibatch_terms(data, mask, logits)
            term = float(terms["style_pair_nll_loss"]) / 3.0
            extras = model.rollout_buffer.sample_extras
            obs = layout.replace_condition(data.observations, extras["swap_condition"][:, 0]) * mask[:, None]
            model.policy.evaluate_actions(obs, data.actions.long().flatten(), data.lstm_states, data.episode_starts)
            swapped = model.policy.action_dist.distribution.logits
            target = extras["swap_action"][:, 0].long()
            ref = -th.log_softmax(swapped, -1)[mask].gather(-1, target[mask][:, None]).mean()
            own = -th.log_softmax(logits, -1)[mask].gather(-1, target[mask][:, None]).mean()
            assert abs(term - float(ref)) < 1e-4
            assert abs(term - float(own)) > 1e-6  # the swapped condition reached the network
            vals.append(term)
        return float(np.mean(vals))

    before = pair_nll()
    model.train()
    assert pair_nll() < 0.8 * before


def test_style_pair_settings():
    with pytest.raises(ValueError, match="style_pairs: the tracking teacher"):
        make_model(teacher="tracking", style_pairs=1)
    with pytest.raises(ValueError, match="style_pairs"):
        make_model(style_pairs=-1)
    with pytest.raises(ValueError, match="style_pair_coef"):
        make_model(style_pairs=1, style_pair_coef=-0.5)
    assert "swap_action" not in make_model().rollout_buffer.extras


def test_the_focused_paired_term_counts_only_decisions_whose_swapped_label_differs():
    model = make_model(style_pairs=1, style_pair_coef=1.0, style_pair_focus=True)
    collect(model)
    layout = model.env.sim.obs_layout
    seen = 0
    for data, mask, logits in minibatch_logits(model):
        term = float(model._minibatch_terms(data, mask, logits)["style_pair_nll_loss"])
        extras = model.rollout_buffer.sample_extras
        target = extras["swap_action"][:, 0].long()
        differ = mask & (target != extras["teacher_action"].reshape(-1).long())
        obs = layout.replace_condition(data.observations, extras["swap_condition"][:, 0]) * mask[:, None]
        model.policy.evaluate_actions(obs, data.actions.long().flatten(), data.lstm_states, data.episode_starts)
        nll = -th.log_softmax(model.policy.action_dist.distribution.logits, -1).gather(-1, target[:, None])[:, 0]
        expected = float(nll[differ].mean()) if differ.any() else 0.0
        assert abs(term - expected) < 1e-4
        assert differ.sum() < mask.sum()  # some swapped labels equal the own one and are left out
        seen += int(differ.sum())
    assert seen > 0
    with pytest.raises(ValueError, match="style_pair_focus"):
        make_model(style_pairs=1, style_pair_focus="yes")
