"""Forward passes of sb3-contrib recurrent policies that return raw logits.

SB3 keeps one shared ``policy.action_dist`` object that every ``get_distribution`` call
mutates, so code that needs two distributions at once (teacher vs. student) silently
compares a distribution with itself. These helpers mirror the policy's own forward code
but return the logits tensor, never touching ``action_dist``.

Only categorical (``Discrete``) action spaces are supported here: CounterPlay samples by
the inverse CDF of a categorical distribution.
"""

from __future__ import annotations

import torch as th
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from sb3_contrib.common.recurrent.type_aliases import RNNStates
from stable_baselines3.common.policies import ActorCriticPolicy

__all__ = ["policy_step_logits", "actor_logits", "critic_values", "inverse_cdf_sample", "zero_states",
           "take_states", "put_states"]

LSTMState = tuple[th.Tensor, th.Tensor]


def policy_step_logits(
    policy: RecurrentActorCriticPolicy,
    obs: th.Tensor,
    lstm_states: RNNStates,
    episode_starts: th.Tensor,
) -> tuple[th.Tensor, th.Tensor, RNNStates]:
    """One actor + critic step, as ``policy.forward`` but returning logits.

    Args:
        obs: (N, D) observations.
        lstm_states: actor and critic (h, c), each (layers, N, hidden).
        episode_starts: (N,) float, 1 where the LSTM state is reset before this step.
    Returns:
        logits (N, n_actions), values (N, 1), new RNNStates.
    """
    features = policy.extract_features(obs)
    if policy.share_features_extractor:
        pi_features = vf_features = features
    else:
        pi_features, vf_features = features
    latent_pi, lstm_pi = policy._process_sequence(pi_features, lstm_states.pi, episode_starts, policy.lstm_actor)
    if policy.lstm_critic is not None:
        latent_vf, lstm_vf = policy._process_sequence(vf_features, lstm_states.vf, episode_starts, policy.lstm_critic)
    elif policy.shared_lstm:
        latent_vf = latent_pi.detach()
        lstm_vf = (lstm_pi[0].detach(), lstm_pi[1].detach())
    else:
        latent_vf = policy.critic(vf_features)
        lstm_vf = lstm_pi
    latent_pi = policy.mlp_extractor.forward_actor(latent_pi)
    latent_vf = policy.mlp_extractor.forward_critic(latent_vf)
    return policy.action_net(latent_pi), policy.value_net(latent_vf), RNNStates(lstm_pi, lstm_vf)


def actor_logits(
    policy: RecurrentActorCriticPolicy,
    obs: th.Tensor,
    lstm_state: LSTMState,
    episode_starts: th.Tensor,
) -> tuple[th.Tensor, LSTMState]:
    """Actor over sequences, as ``policy.get_distribution`` but returning logits.

    Args:
        obs: (n_seq * seq_len, D), sequence-major (all steps of sequence 0 first).
        lstm_state: (h, c), each (layers, n_seq, hidden): memory before the first step.
        episode_starts: (n_seq * seq_len,) float.
    Returns:
        logits (n_seq * seq_len, n_actions) and the final LSTM state.
    """
    features = super(ActorCriticPolicy, policy).extract_features(obs, policy.pi_features_extractor)
    latent_pi, state = policy._process_sequence(features, lstm_state, episode_starts, policy.lstm_actor)
    return policy.action_net(policy.mlp_extractor.forward_actor(latent_pi)), state


def critic_values(
    policy: RecurrentActorCriticPolicy,
    obs: th.Tensor,
    lstm_state: LSTMState,
    episode_starts: th.Tensor,
) -> th.Tensor:
    """Critic over sequences (same layout as :func:`actor_logits`): values (n_seq * seq_len, 1)."""
    return policy.predict_values(obs, lstm_state, episode_starts)


def inverse_cdf_sample(logits: th.Tensor, uniforms: th.Tensor) -> th.Tensor:
    """Sample categorical actions by the inverse CDF of ``softmax(logits)``.

    With the same uniform, two distributions that differ a little pick the same or an
    adjacent action: the basis of shared randomness across branches.

    Args:
        logits: (N, n_actions).
        uniforms: (N,) in [0, 1).
    Returns:
        (N,) int64 actions.
    """
    probs = th.softmax(logits.float(), dim=-1)
    cdf = th.cumsum(probs, dim=-1)
    # scale by the total so float rounding of the cumsum never leaves u above the last bin
    target = uniforms.to(cdf.dtype).reshape(-1, 1) * cdf[:, -1:]
    actions = th.searchsorted(cdf, target, right=True).reshape(-1)
    return actions.clamp_(max=logits.shape[-1] - 1)


def zero_states(policy: RecurrentActorCriticPolicy, n: int, device: th.device | str) -> RNNStates:
    """Zero actor and critic LSTM states for ``n`` sequences."""
    lstm = policy.lstm_actor
    shape = (lstm.num_layers, n, lstm.hidden_size)
    z = lambda: th.zeros(shape, device=device)  # noqa: E731
    return RNNStates((z(), z()), (z(), z()))


def take_states(states: RNNStates, idx: th.Tensor) -> RNNStates:
    """The columns ``idx`` of actor and critic (h, c), each (layers, N, hidden)."""
    return RNNStates((states.pi[0][:, idx], states.pi[1][:, idx]), (states.vf[0][:, idx], states.vf[1][:, idx]))


def put_states(states: RNNStates, idx: th.Tensor, part: RNNStates) -> RNNStates:
    """``states`` with the columns ``idx`` replaced by ``part`` (inactive slots keep their
    memory; they restart with an episode start when they come back)."""
    def put(full: th.Tensor, sub: th.Tensor) -> th.Tensor:
        out = full.clone()
        out[:, idx] = sub
        return out

    return RNNStates((put(states.pi[0], part.pi[0]), put(states.pi[1], part.pi[1])),
                     (put(states.vf[0], part.vf[0]), put(states.vf[1], part.vf[1])))
