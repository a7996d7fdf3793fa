"""Recurrent rollout buffers that also store which slots were active.

``SelfPlayVecEnv`` has one env index per agent slot; slots without a live agent emit a zero
observation and reward 0. Their transitions are stored (the buffer layout is fixed) but
must not reach any loss or the advantage normalisation. sb3-contrib's recurrent
``train`` already restricts every mean to ``samples.mask`` (the padding mask); these
buffers multiply that mask by the stored activity flag, so the parent's loss code masks
inactive slots with no further change.

With every slot active the samples are exactly the parent's (same mask tensor, same
random split), which keeps ``CounterPlay`` bit-identical to ``RecurrentPPO`` when its
features are off.
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any

import numpy as np
from sb3_contrib.common.recurrent.buffers import RecurrentDictRolloutBuffer, RecurrentRolloutBuffer

__all__ = ["MaskedRecurrentRolloutBuffer", "MaskedRecurrentDictRolloutBuffer"]


class _ActiveMaskMixin:
    """Adds ``active`` (n_steps, n_envs) float32 to a recurrent rollout buffer."""

    active: np.ndarray

    def reset(self) -> None:
        super().reset()  # type: ignore[misc]
        self.active = np.ones((self.buffer_size, self.n_envs), dtype=np.float32)  # type: ignore[attr-defined]

    def add(self, *args: Any, active: np.ndarray | None = None, **kwargs: Any) -> None:
        """Add one step; ``active`` (n_envs,) bool marks the slots whose data counts
        (default: all). Must be given before the parent increments ``pos``."""
        if active is not None:
            self.active[self.pos] = np.asarray(active, dtype=np.float32).reshape(-1)  # type: ignore[attr-defined]
        super().add(*args, **kwargs)  # type: ignore[misc]

    def get(self, batch_size: int | None = None) -> Generator[Any, None, None]:
        if not self.generator_ready:  # type: ignore[attr-defined]
            # flattened in the same order as every other field (parent flattens on first use)
            self.active = self.swap_and_flatten(self.active)  # type: ignore[attr-defined]
        yield from super().get(batch_size)  # type: ignore[misc]

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
