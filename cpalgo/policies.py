"""Recurrent actor-critic policies whose LSTM runs a whole padded sequence in one call.

sb3-contrib's :meth:`RecurrentActorCriticPolicy._process_sequence` steps the LSTM one
decision at a time whenever any padded sequence of a minibatch contains an episode start.
``RecurrentRolloutBuffer`` starts a new sequence at every episode start, so a start can only
ever be a sequence's *first* element; with many parallel episodes nearly every minibatch has
one and the slow path is the rule. Zeroing the initial ``(h, c)`` of the sequences that start
an episode and running the whole sequence in one ``nn.LSTM`` call computes the same function
(equal to float rounding) several times faster. The stepping path is kept for the case the
fused call cannot express: a start *inside* a sequence.

The classes here are drop-in replacements any sb3-contrib user can pass to plain
``RecurrentPPO``::

    from sb3_contrib import RecurrentPPO
    from cpalgo.policies import MlpLstmPolicy
    RecurrentPPO(MlpLstmPolicy, env)

``CounterPlay("MlpLstmPolicy", env)`` uses them by default (``CounterPlay.policy_aliases``).
"""

from __future__ import annotations

import torch as th
from sb3_contrib.common.recurrent.policies import (
    RecurrentActorCriticCnnPolicy,
    RecurrentActorCriticPolicy,
    RecurrentMultiInputActorCriticPolicy,
)
from torch import nn

__all__ = [
    "fused_process_sequence",
    "FusedLstmMixin",
    "MlpLstmPolicy",
    "CnnLstmPolicy",
    "MultiInputLstmPolicy",
    "POLICY_ALIASES",
]

LSTMState = tuple[th.Tensor, th.Tensor]


def fused_process_sequence(
    features: th.Tensor,
    lstm_states: LSTMState,
    episode_starts: th.Tensor,
    lstm: nn.LSTM,
) -> tuple[th.Tensor, LSTMState]:
    """LSTM over padded sequences, one ``nn.LSTM`` call when starts are only at the front.

    Same contract as sb3-contrib's ``_process_sequence``.

    Args:
        features: (n_seq * seq_len, input_size), sequence-major (all steps of sequence 0
            first); ``seq_len`` is 1 during rollouts.
        lstm_states: (h, c), each (layers, n_seq, hidden): memory before the first step.
        episode_starts: (n_seq * seq_len,) float, 1 where the memory is reset before a step.
        lstm: the LSTM module.
    Returns:
        outputs (n_seq * seq_len, hidden) and the final (h, c).
    """
    n_seq = lstm_states[0].shape[1]
    features_sequence = features.reshape((n_seq, -1, lstm.input_size)).swapaxes(0, 1)
    starts = episode_starts.reshape((n_seq, -1)).swapaxes(0, 1)  # (seq_len, n_seq)
    if starts.shape[0] > 1 and bool(starts[1:].any()):
        # a start inside a sequence: the memory must be cut mid-call, which one fused
        # call cannot do; step as sb3-contrib does
        return RecurrentActorCriticPolicy._process_sequence(features, lstm_states, episode_starts, lstm)
    keep = (1.0 - starts[0]).view(1, n_seq, 1)
    output, final = lstm(features_sequence, (keep * lstm_states[0], keep * lstm_states[1]))
    return th.flatten(output.transpose(0, 1), start_dim=0, end_dim=1), final


class FusedLstmMixin:
    """Replaces ``_process_sequence`` of a sb3-contrib recurrent policy by the fused one.

    Used for the actor LSTM, the critic LSTM (when ``enable_critic_lstm``) and every
    caller that goes through ``_process_sequence`` (``evaluate_actions``,
    ``get_distribution``, ``predict_values``, the distillation student pass).
    """

    _process_sequence = staticmethod(fused_process_sequence)


class MlpLstmPolicy(FusedLstmMixin, RecurrentActorCriticPolicy):
    """:class:`RecurrentActorCriticPolicy` with the fused sequence LSTM."""


class CnnLstmPolicy(FusedLstmMixin, RecurrentActorCriticCnnPolicy):
    """:class:`RecurrentActorCriticCnnPolicy` with the fused sequence LSTM."""


class MultiInputLstmPolicy(FusedLstmMixin, RecurrentMultiInputActorCriticPolicy):
    """:class:`RecurrentMultiInputActorCriticPolicy` with the fused sequence LSTM."""


#: names accepted by ``CounterPlay(policy=...)``: the fused versions of sb3-contrib's
POLICY_ALIASES: dict[str, type[RecurrentActorCriticPolicy]] = {
    "MlpLstmPolicy": MlpLstmPolicy,
    "CnnLstmPolicy": CnnLstmPolicy,
    "MultiInputLstmPolicy": MultiInputLstmPolicy,
}
