"""SPICED adapted to recurrent self-play driving (the seed paper's SPICED-dagger baseline).

The original (Cornelisse et al., 2026; after HR-PPO) keeps self-play PPO human-like by
adding a KL penalty between the learning policy and a frozen behaviour-cloning policy
trained on human driving logs, weighted by a small coefficient.

Adaptation (:class:`Spiced`): the reference is trained on *log-tracking* actions of the
run's own training scenarios (:func:`cpalgo.baselines.spiced.reference.tracking_reference`:
:class:`cpsim.expert.TrackingExpert` labels cloned by a :class:`cpalgo.traffic.bc.BCPolicy`, the
condition slice zeroed), or is the shipped ``cpalgo.traffic`` model when it fits the policy's
observation and action space (``reference="shipped"`` or a checkpoint path). During the
rollout the reference's logits are stored for every live decision; every PPO minibatch
adds ``kl_coef`` x the masked mean of KL(pi_ref || pi) (``kl_direction="forward"``,
HR-PPO's mass-covering direction) or KL(pi || pi_ref) (``"reverse"``) on the same
decisions. The rest is PPO-Continue (masked self-play PPO on the main rollout).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch as th
from sb3_contrib.common.recurrent.type_aliases import RNNStates

from cpalgo.baselines.spiced.reference import ReferenceStepper, load_reference, tracking_reference
from cpalgo.common.hooked_train import HookedPPO, categorical_kl, check_number, masked_mean
from cpalgo.methods.base import base_vec_env

__all__ = ["Spiced", "KL_DIRECTIONS"]

#: forward: KL(reference || policy); reverse: KL(policy || reference)
KL_DIRECTIONS: tuple[str, ...] = ("forward", "reverse")


class Spiced(HookedPPO):
    """SPICED-dagger (see the module docstring).

    Args:
        kl_coef: weight of the KL penalty (0.05).
        kl_direction: ``forward`` (KL(pi_ref || pi), default) or ``reverse``.
        reference: ``tracking`` (clone TrackingExpert labels on the training scenarios, at
            :meth:`on_anchor_loaded` or the first rollout), ``shipped`` (``zoo/bc_traffic.pt``)
            or the path of a ``python -m cpalgo.traffic`` checkpoint.
        reference_worlds, reference_episodes: worlds per batch and batches of expert
            episodes for ``tracking`` (16, 2).
        reference_epochs, reference_hidden: BC epochs and hidden width (10, 128).
        Other arguments: :class:`cpalgo.common.hooked_train.HookedPPO`'s and PPO's.

    Attributes:
        reference_policy: the frozen reference (saved with the model); assign a module
            ``obs -> logits`` or a recurrent SB3 policy to use another one.
        reference_metrics: the BC fit's metrics (``tracking``).
    """

    _RUNTIME_ATTRS: ClassVar[tuple[str, ...]] = HookedPPO._RUNTIME_ATTRS + ("_ref_stepper", "_kl_raw")

    def __init__(self, policy: Any, env: Any, kl_coef: float = 0.05, kl_direction: str = "forward",
                 reference: str = "tracking", reference_worlds: int = 16, reference_episodes: int = 2,
                 reference_epochs: int = 10, reference_hidden: int = 128, **kwargs: Any) -> None:
        self.kl_coef = kl_coef
        self.kl_direction = kl_direction
        self.reference = reference
        self.reference_worlds = reference_worlds
        self.reference_episodes = reference_episodes
        self.reference_epochs = reference_epochs
        self.reference_hidden = reference_hidden
        self.reference_policy: Any = None
        self.reference_metrics: dict[str, float] = {}
        super().__init__(policy, env, **kwargs)

    def _validate_settings(self) -> None:
        super()._validate_settings()
        check_number("kl_coef", self.kl_coef, low=0.0)
        if self.kl_direction not in KL_DIRECTIONS:
            raise ValueError(f"kl_direction: expected one of {KL_DIRECTIONS}, got {self.kl_direction!r}")
        if not isinstance(self.reference, str) or not self.reference:
            raise ValueError(f"reference: expected 'tracking', 'shipped' or a checkpoint path, got {self.reference!r}")
        for name in ("reference_worlds", "reference_episodes", "reference_epochs", "reference_hidden"):
            check_number(name, getattr(self, name), low=1, integer=True)

    def _extra_shapes(self) -> dict[str, tuple[int, ...]]:
        return {"ref_logits": (int(self.action_space.n),)}

    def _reset_runtime(self) -> None:
        super()._reset_runtime()
        self._ref_stepper: ReferenceStepper | None = None
        self._kl_raw: list[float] = []

    # ------------------------------------------------------------------ reference
    def build_reference(self) -> Any:
        """The reference of the ``reference`` setting (trained or loaded now)."""
        if self.reference == "tracking":
            sim = base_vec_env(self.env).sim
            model, self.reference_metrics = tracking_reference(
                self.policy, sim, num_worlds=int(self.reference_worlds), episodes=int(self.reference_episodes),
                epochs=int(self.reference_epochs), hidden=int(self.reference_hidden), seed=int(self.seed or 0))
            return model.to(self.device)
        path = "zoo/bc_traffic.pt" if self.reference == "shipped" else self.reference
        return load_reference(path, int(self.observation_space.shape[0]), int(self.action_space.n)).to(self.device)

    def on_anchor_loaded(self) -> None:
        """Build the reference (once; a reference already set is kept)."""
        if self.reference_policy is None:
            self.reference_policy = self.build_reference()
        self._ref_stepper = None

    def _stepper(self, n: int) -> ReferenceStepper:
        if self.reference_policy is None:
            self.on_anchor_loaded()
        if self._ref_stepper is None or self._ref_stepper.reference is not self.reference_policy:
            self._ref_stepper = ReferenceStepper(self.reference_policy, n, self.device)
        return self._ref_stepper

    # ------------------------------------------------------------------ rollout
    def _policy_step(self, env: Any, obs_tensor: th.Tensor, lstm_states: RNNStates, episode_starts: th.Tensor
                     ) -> tuple[th.Tensor, th.Tensor, th.Tensor, RNNStates]:
        out = super()._policy_step(env, obs_tensor, lstm_states, episode_starts)
        n = obs_tensor.shape[0]
        idx = self._active_index(n)
        logits = self._stepper(n).step(obs_tensor, episode_starts, idx)
        rows = np.arange(n) if idx is None else idx.cpu().numpy()
        self.rollout_buffer.extras["ref_logits"][self.rollout_buffer.pos, rows] = logits.cpu().numpy()
        return out

    def _on_env_reset(self) -> None:
        super()._on_env_reset()
        self._ref_stepper = None  # every slot starts a new episode

    # ------------------------------------------------------------------ loss
    def _minibatch_terms(self, rollout_data: Any, mask: th.Tensor, logits: th.Tensor) -> dict[str, th.Tensor]:
        ref = self.rollout_buffer.sample_extras["ref_logits"]
        kl = categorical_kl(ref, logits) if self.kl_direction == "forward" else categorical_kl(logits, ref)
        value = masked_mean(kl, mask)
        self._kl_raw.append(float(value.item()))
        return {"spiced_kl_loss": float(self.kl_coef) * value}

    def _after_train(self) -> None:
        if self._kl_raw:
            self.logger.record("train/spiced_kl", float(np.mean(self._kl_raw)))
        self._kl_raw = []
        super()._after_train()
