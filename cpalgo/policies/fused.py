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

from collections.abc import Iterator
from contextlib import contextmanager

import torch as th
from sb3_contrib.common.recurrent.policies import (
    RecurrentActorCriticCnnPolicy,
    RecurrentActorCriticPolicy,
    RecurrentMultiInputActorCriticPolicy,
)
from torch import nn

__all__ = [
    "fused_process_sequence",
    "sequence_lengths",
    "lengths_from_mask",
    "FusedLstmMixin",
    "MlpLstmPolicy",
    "CnnLstmPolicy",
    "MultiInputLstmPolicy",
]

LSTMState = tuple[th.Tensor, th.Tensor]

#: length buckets only pay when the padded minibatch is this much larger than its counted
#: steps: measured on 2 CPU cores, buckets took 17 % off ``train`` at 1.75x padding (16 x 8
#: slots, 64-step rollouts) and were within noise, a few more calls, at 1.11x (64 x 8, 32 steps)
BUCKET_MIN_PADDING = 1.25


def fused_process_sequence(
    features: th.Tensor,
    lstm_states: LSTMState,
    episode_starts: th.Tensor,
    lstm: nn.LSTM,
    lengths: th.Tensor | None = None,
) -> tuple[th.Tensor, LSTMState]:
    """LSTM over padded sequences, one ``nn.LSTM`` call when starts are only at the front.

    Same contract as sb3-contrib's ``_process_sequence``. With ``lengths`` the sequences run
    in length buckets (:func:`_bucketed_lstm`): most padding after each sequence's last
    counted step is skipped, and the output there is 0 instead of the LSTM's response to
    zero input (callers must mask those rows out, as every PPO loss already does). The
    counted rows are the same function; the final state is then not meaningful.

    Args:
        features: (n_seq * seq_len, input_size), sequence-major (all steps of sequence 0
            first); ``seq_len`` is 1 during rollouts.
        lstm_states: (h, c), each (layers, n_seq, hidden): memory before the first step.
        episode_starts: (n_seq * seq_len,) float, 1 where the memory is reset before a step.
        lstm: the LSTM module.
        lengths: optional (n_seq,) int64 on the CPU, each in [1, seq_len]: the steps of each
            sequence that count (see :func:`sequence_lengths`); ignored when its size does
            not match ``n_seq`` or when padding is under ``BUCKET_MIN_PADDING`` of the steps.
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
    initial = (keep * lstm_states[0], keep * lstm_states[1])
    seq_len = features_sequence.shape[0]
    if (lengths is not None and lengths.numel() == n_seq and seq_len > 1
            and n_seq * seq_len > BUCKET_MIN_PADDING * int(lengths.sum())):
        output, final = _bucketed_lstm(features_sequence, initial, lengths, lstm)
    else:
        output, final = lstm(features_sequence, initial)
    return th.flatten(output.transpose(0, 1), start_dim=0, end_dim=1), final


def _bucketed_lstm(features_sequence: th.Tensor, initial: LSTMState, lengths: th.Tensor, lstm: nn.LSTM,
                   n_buckets: int = 4) -> tuple[th.Tensor, LSTMState]:
    """One padded ``nn.LSTM`` call per length bucket (quarters of ``seq_len``), each cut to
    the longest sequence it holds.

    Why not ``pack_padded_sequence``: on CPU a packed LSTM leaves oneDNN for the native
    kernel, whose backward zero-fills a full-size gradient at every step; it measured no
    faster than the padded call. Buckets keep oneDNN and drop most of the padding.

    Args:
        features_sequence: (seq_len, n_seq, input_size).
        initial: (h, c), each (layers, n_seq, hidden), already zeroed at episode starts.
        lengths: (n_seq,) int64 CPU, each in [1, seq_len].
    Returns:
        output (seq_len, n_seq, hidden), 0 after each sequence's length, and (h, c) after
        each bucket's last step (training passes discard it).
    """
    seq_len, n_seq = features_sequence.shape[:2]
    device = features_sequence.device
    edges = sorted({-(-seq_len * k // n_buckets) for k in range(1, n_buckets + 1)})
    output: th.Tensor | None = None
    h_n: th.Tensor | None = None
    c_n: th.Tensor | None = None
    low = 0
    for high in edges:
        picked = ((lengths > low) & (lengths <= high)).nonzero().squeeze(1)
        low = high
        if picked.numel() == 0:
            continue
        steps = int(lengths[picked].max())
        index = picked.to(device)
        out, (h, c) = lstm(features_sequence[:steps].index_select(1, index),
                           (initial[0].index_select(1, index), initial[1].index_select(1, index)))
        if output is None:
            output = out.new_zeros(seq_len, n_seq, out.shape[2])
            h_n, c_n = h.new_zeros(h.shape[0], n_seq, h.shape[2]), c.new_zeros(c.shape[0], n_seq, c.shape[2])
        output = output.index_copy(1, index, nn.functional.pad(out, (0, 0, 0, 0, 0, seq_len - steps)))
        h_n, c_n = h_n.index_copy(1, index, h), c_n.index_copy(1, index, c)
    assert output is not None and h_n is not None and c_n is not None
    return output, (h_n, c_n)


def lengths_from_mask(mask: th.Tensor, n_seq: int) -> th.Tensor:
    """Counted length of each padded sequence: one past its last nonzero mask entry.

    Args:
        mask: (n_seq * seq_len,) the loss mask of a minibatch (padding and, masked,
            inactive steps are 0); only trailing zeros are cut, so a zero inside a
            sequence still carries the memory through that step.
        n_seq: number of sequences.
    Returns:
        (n_seq,) int64 on the CPU, each at least 1.
    """
    rows = (mask.detach().reshape(n_seq, -1) != 0).cpu()
    seq_len = rows.shape[1]
    last = seq_len - th.argmax(rows.flip(1).to(th.int8), dim=1)
    return th.where(rows.any(dim=1), last, th.ones_like(last)).to(th.int64)


@contextmanager
def sequence_lengths(policy: nn.Module, mask: th.Tensor, n_seq: int) -> Iterator[None]:
    """Within the block, a fused policy runs its training-sequence LSTM calls in length buckets.

    ``sb3-contrib`` pads every sequence of a minibatch to the longest (1.1-1.8x the real
    steps with 32-64-step rollouts); the mask knows where the padding is, the policy does
    not (plain ``RecurrentPPO`` passes no mask, so there the policy keeps the padded call).
    Policies without the fused mixin ignore this.

    Args:
        policy: the policy whose ``evaluate_actions`` / ``get_distribution`` follows.
        mask: (n_seq * seq_len,) minibatch loss mask (``rollout_data.mask``).
        n_seq: sequences in the minibatch (``rollout_data.lstm_states.pi[0].shape[1]``).
    """
    if not isinstance(policy, FusedLstmMixin):
        yield
        return
    previous = policy._sequence_lengths
    policy._sequence_lengths = lengths_from_mask(mask, n_seq)
    try:
        yield
    finally:
        policy._sequence_lengths = previous


class FusedLstmMixin:
    """Replaces ``_process_sequence`` of a sb3-contrib recurrent policy by the fused one.

    Used for the actor LSTM, the critic LSTM (when ``enable_critic_lstm``) and every
    caller that goes through ``_process_sequence`` (``evaluate_actions``,
    ``get_distribution``, ``predict_values``, the distillation student pass).
    """

    #: (n_seq,) counted lengths of the minibatch being evaluated (:func:`sequence_lengths`)
    _sequence_lengths: th.Tensor | None = None

    def _process_sequence(self, features: th.Tensor, lstm_states: LSTMState, episode_starts: th.Tensor,
                          lstm: nn.LSTM) -> tuple[th.Tensor, LSTMState]:
        return fused_process_sequence(features, lstm_states, episode_starts, lstm, self._sequence_lengths)


class MlpLstmPolicy(FusedLstmMixin, RecurrentActorCriticPolicy):
    """:class:`RecurrentActorCriticPolicy` with the fused sequence LSTM."""


class CnnLstmPolicy(FusedLstmMixin, RecurrentActorCriticCnnPolicy):
    """:class:`RecurrentActorCriticCnnPolicy` with the fused sequence LSTM."""


class MultiInputLstmPolicy(FusedLstmMixin, RecurrentMultiInputActorCriticPolicy):
    """:class:`RecurrentMultiInputActorCriticPolicy` with the fused sequence LSTM."""
