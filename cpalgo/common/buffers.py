"""Recurrent rollout buffers that know which slots were active.

``SelfPlayVecEnv`` has one env index per agent slot; slots without a live agent emit a zero
observation and reward 0. Their transitions are stored (the buffer layout is fixed) but
must not reach any loss or the advantage normalisation.

Two ways of keeping them out:

* ``active_only=True`` (CounterPlay's default with ``mask_inactive``): minibatches are built
  from the active transitions alone, so inactive slots cost no forward or backward pass.
  ``batch_size`` then counts active transitions. A new padded sequence starts at every
  episode start, at the first step of each env's data, and after every inactive gap, so
  the LSTM memory bookkeeping is the parent's on the data that remains. Padding is one
  vectorised scatter per field instead of one tensor per sequence.
* ``active_only=False``: the parent's minibatches over every transition, with the padding
  mask multiplied by the activity flag; sb3-contrib's recurrent ``train`` restricts every
  mean to ``samples.mask``, so the losses ignore inactive slots with no further change.

With every slot active the samples are exactly the parent's (same mask tensor, same
random split), which keeps ``CounterPlay`` bit-identical to ``RecurrentPPO`` when its
features are off.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from typing import Any

import numpy as np
import torch as th
from sb3_contrib.common.recurrent.buffers import RecurrentDictRolloutBuffer, RecurrentRolloutBuffer
from sb3_contrib.common.recurrent.type_aliases import (
    RecurrentDictRolloutBufferSamples,
    RecurrentRolloutBufferSamples,
    RNNStates,
)

__all__ = ["MaskedRecurrentRolloutBuffer", "MaskedRecurrentDictRolloutBuffer", "padded_sequencer"]

_FLAT_FIELDS = ("actions", "values", "log_probs", "advantages", "returns",
                "hidden_states_pi", "cell_states_pi", "hidden_states_vf", "cell_states_vf", "episode_starts")
_STATE_FIELDS = ("hidden_states_pi", "cell_states_pi", "hidden_states_vf", "cell_states_vf")


def padded_sequencer(seq_start: np.ndarray, device: th.device | str) -> tuple[np.ndarray, int, Callable[[np.ndarray], th.Tensor]]:
    """Sequence layout of a minibatch and a vectorised padding function.

    Args:
        seq_start: (n,) bool, True where a new sequence starts (element 0 always does).
    Returns:
        start indices (n_seq,), the padded length, and ``pad(x)``: (n, *shape) numpy ->
        (n_seq, max_len, *shape) tensor, zero-padded at the end of each sequence.
    """
    seq_start = np.asarray(seq_start, bool).copy()
    seq_start[0] = True
    starts = np.flatnonzero(seq_start)
    seq_id = np.cumsum(seq_start) - 1
    pos = np.arange(seq_start.size) - starts[seq_id]
    max_len = int(pos.max()) + 1

    def pad(x: np.ndarray) -> th.Tensor:
        out = np.zeros((starts.size, max_len, *x.shape[1:]), dtype=x.dtype)
        out[seq_id, pos] = x
        return th.as_tensor(out, device=device)

    return starts, max_len, pad


class _ActiveMaskMixin:
    """Adds ``active`` (n_steps, n_envs) float32 and active-only minibatches."""

    active: np.ndarray
    #: build minibatches from active transitions only (see the module docstring)
    active_only: bool = False

    def reset(self) -> None:
        # a rollout cut short by the budget (truncate) shrank buffer_size: restore it
        self.buffer_size = self.__dict__.setdefault("_full_size", self.buffer_size)  # type: ignore[attr-defined]
        super().reset()  # type: ignore[misc]
        self.active = np.ones((self.buffer_size, self.n_envs), dtype=np.float32)  # type: ignore[attr-defined]

    def truncate(self, steps: int) -> None:
        """Keep the first ``steps`` rows of a rollout that stopped early (the post-training
        budget was reached mid-rollout): every (n_steps, ...) array is cut, the buffer
        counts as full, and GAE bootstraps from the value after the last kept step, as at
        the end of a full rollout. The next :meth:`reset` restores the full size."""
        steps = int(steps)
        size = int(self.buffer_size)  # type: ignore[attr-defined]
        if self.generator_ready:  # type: ignore[attr-defined]
            raise ValueError("truncate: the buffer was already flattened for sampling")
        if not 1 <= steps <= size or steps != int(self.pos):  # type: ignore[attr-defined]
            raise ValueError(f"steps: expected the {self.pos} rows added so far (1..{size}), got {steps}")  # type: ignore[attr-defined]
        if steps == size:
            return
        for name, value in list(self.__dict__.items()):
            if isinstance(value, np.ndarray) and value.ndim >= 1 and value.shape[0] == size:
                self.__dict__[name] = value[:steps].copy()
            elif isinstance(value, dict) and value and all(
                    isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == size for v in value.values()):
                self.__dict__[name] = {k: v[:steps].copy() for k, v in value.items()}
        self.buffer_size = steps  # type: ignore[attr-defined]
        self.full = True  # type: ignore[attr-defined]

    def add(self, *args: Any, active: np.ndarray | None = None, **kwargs: Any) -> None:
        """Add one step; ``active`` (n_envs,) bool marks the slots whose data counts
        (default: all). Must be given before the parent increments ``pos``."""
        if active is not None:
            self.active[self.pos] = np.asarray(active, dtype=np.float32).reshape(-1)  # type: ignore[attr-defined]
        super().add(*args, **kwargs)  # type: ignore[misc]

    # ------------------------------------------------------------------ sampling
    def _uses_active_path(self) -> bool:
        return bool(self.active_only) and not bool(np.all(self.active))

    def num_minibatches(self, batch_size: int | None) -> int:
        """Minibatches one pass of :meth:`get` yields (for scheduling extra loss terms)."""
        n = int(np.count_nonzero(self.active)) if self._uses_active_path() else self.active.size
        if n == 0:
            return 0
        return 1 if batch_size is None else -(-n // int(batch_size))

    def get(self, batch_size: int | None = None) -> Generator[Any, None, None]:
        if not self._uses_active_path():
            if not self.generator_ready:  # type: ignore[attr-defined]
                # flattened in the same order as every other field (parent flattens on first use)
                self.active = self.swap_and_flatten(self.active)  # type: ignore[attr-defined]
            yield from super().get(batch_size)  # type: ignore[misc]
            return
        assert self.full, "Rollout buffer must be full before sampling from it"  # type: ignore[attr-defined]
        self._flatten_fields()
        active = self.active.reshape(-1) > 0
        index = np.flatnonzero(active)
        if index.size == 0:
            return
        seq_start = self._sequence_starts(active)
        if batch_size is None:
            batch_size = index.size
        # the parent's shuffle: keep the sequence order but rotate at a random point
        split = np.random.randint(index.size)
        order = np.concatenate((index[split:], index[:split]))
        for start in range(0, order.size, int(batch_size)):
            batch_inds = order[start : start + int(batch_size)]
            yield self._active_samples(batch_inds, seq_start[batch_inds])

    def _sequence_starts(self, active: np.ndarray) -> np.ndarray:
        """(n_envs * n_steps,) bool over the flattened buffer: a sequence starts at an episode
        start, at each env's first step, and after an inactive gap (the memory stored there
        belongs to that step, not to the gap). Subclasses add their own cuts."""
        env_first = np.zeros((self.n_envs, self.buffer_size), bool)  # type: ignore[attr-defined]
        env_first[:, 0] = True
        after_gap = np.ones_like(active)
        after_gap[1:] = ~active[:-1]
        return (self.episode_starts.reshape(-1) > 0) | env_first.reshape(-1) | after_gap  # type: ignore[attr-defined]

    def _flatten_fields(self) -> None:
        """The parent's one-time (n_steps, n_envs, ...) -> (n_envs * n_steps, ...) flatten."""
        if self.generator_ready:  # type: ignore[attr-defined]
            return
        d = self.__dict__
        for name in _STATE_FIELDS:
            d[name] = d[name].swapaxes(1, 2)
        if isinstance(self.observations, dict):  # type: ignore[attr-defined]
            for key, obs in self.observations.items():  # type: ignore[attr-defined]
                self.observations[key] = self.swap_and_flatten(obs)  # type: ignore[attr-defined]
        else:
            d["observations"] = self.swap_and_flatten(d["observations"])  # type: ignore[attr-defined]
        for name in (*_FLAT_FIELDS, "active"):
            d[name] = self.swap_and_flatten(d[name])  # type: ignore[attr-defined]
        self.generator_ready = True

    def _active_samples(self, batch_inds: np.ndarray, seq_start: np.ndarray) -> Any:
        """Padded sequences of the given active transitions (same fields as the parent)."""
        starts, max_len, pad = padded_sequencer(seq_start, self.device)  # type: ignore[attr-defined]
        padded = starts.size * max_len
        first = batch_inds[starts]

        def state(name: str) -> th.Tensor:
            # (n_envs * n_steps, layers, hidden) -> (layers, n_seq, hidden)
            return self.to_torch(self.__dict__[name][first].swapaxes(0, 1)).contiguous()  # type: ignore[attr-defined]

        def flat(name: str) -> th.Tensor:
            return pad(self.__dict__[name][batch_inds]).reshape(padded)

        lstm_states = RNNStates((state("hidden_states_pi"), state("cell_states_pi")),
                                (state("hidden_states_vf"), state("cell_states_vf")))
        fields = dict(
            actions=pad(self.actions[batch_inds]).reshape((padded, *self.actions.shape[1:])),  # type: ignore[attr-defined]
            old_values=flat("values"),
            old_log_prob=flat("log_probs"),
            advantages=flat("advantages"),
            returns=flat("returns"),
            lstm_states=lstm_states,
            episode_starts=flat("episode_starts"),
            mask=pad(np.ones(batch_inds.size, np.float32)).reshape(padded),
        )
        if isinstance(self.observations, dict):  # type: ignore[attr-defined]
            obs = {key: pad(value[batch_inds]).reshape((padded, *self.obs_shape[key]))  # type: ignore[attr-defined]
                   for key, value in self.observations.items()}  # type: ignore[attr-defined]
            return RecurrentDictRolloutBufferSamples(observations=obs, **fields)
        obs = pad(self.observations[batch_inds]).reshape((padded, *self.obs_shape))  # type: ignore[attr-defined]
        return RecurrentRolloutBufferSamples(observations=obs, **fields)

    def _get_samples(self, batch_inds: np.ndarray, env_change: np.ndarray, env: Any = None) -> Any:
        samples = super()._get_samples(batch_inds, env_change, env)  # type: ignore[misc]
        active = self.active[batch_inds]
        if active.all():
            return samples  # the parent's padding mask already is the answer
        # padding stays 0 (pad value), inactive steps become 0 too
        return samples._replace(mask=self.pad_and_flatten(active))  # type: ignore[attr-defined]

    @property
    def active_fraction(self) -> float:
        """Share of stored transitions that belong to active slots."""
        return float(np.mean(self.active))


class MaskedRecurrentRolloutBuffer(_ActiveMaskMixin, RecurrentRolloutBuffer):
    """:class:`RecurrentRolloutBuffer` with an activity mask (Box observations)."""


class MaskedRecurrentDictRolloutBuffer(_ActiveMaskMixin, RecurrentDictRolloutBuffer):
    """:class:`RecurrentDictRolloutBuffer` with an activity mask (Dict observations)."""
