"""Observation encoder: shrink the 699-wide driving observation before the LSTM.

The stock recurrent policies feed the flat observation straight into the LSTM and, without a
critic LSTM, into the critic's first layer. Those input projections (``4 * hidden`` + the
critic's width rows of 699 weights each, 640 x 699 for the anchor's network) are most of
the training FLOPs on a CPU (BENCHMARKS.md). :class:`LinearEncoder` puts one shared linear
map of ``features_dim`` outputs in front of both, so the projection becomes
``features_dim x 699`` plus ``640 x features_dim``: 2.6x fewer multiply-adds at 128.

A trained flat network converts without retraining: :func:`factorize_input_layers` solves the
reduced-rank regression of the stacked input weights on observations the policy actually sees
(the best rank-``features_dim`` map for that data), so the converted policy's input
projections are close to the original's; ``counterplay compress-anchor`` (:mod:`cpalgo.anchor.compress`)
wraps it for checkpoints and distills the rest of the difference away.

Use it through ``policy_kwargs`` with any SB3 / sb3-contrib policy::

    from cpalgo.encoders import LinearEncoder
    policy_kwargs = dict(features_extractor_class=LinearEncoder,
                         features_extractor_kwargs=dict(features_dim=128))
    CounterPlay("MlpLstmPolicy", env, policy_kwargs=policy_kwargs)
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

__all__ = ["FEATURE_EXTRACTORS", "ConditionConcat", "ConditionResidual", "LinearEncoder", "add_condition_branch", "encoder_policy_kwargs",
           "factorize_input_layers", "input_weight_rows"]


class LinearEncoder(BaseFeaturesExtractor):
    """One linear map, no bias, no activation: ``features = E @ obs``.

    With the LSTM's input weights after it, it is a rank-``features_dim`` factorisation of the
    LSTM's (and the critic's) input projection; the layers after it keep their biases.

    Args:
        observation_space: flat Box of D values.
        features_dim: output width (the LSTM's input size), at most D.
    Shapes:
        forward: (B, D) float -> (B, features_dim).
    """

    def __init__(self, observation_space: gym.Space, features_dim: int = 128) -> None:
        if not isinstance(observation_space, gym.spaces.Box) or len(observation_space.shape) != 1:
            raise ValueError(f"observation_space: LinearEncoder needs a flat Box, got {observation_space}")
        size = int(observation_space.shape[0])
        if not 0 < int(features_dim) <= size:
            raise ValueError(f"features_dim: must lie in [1, {size}] (the observation size), got {features_dim}")
        super().__init__(observation_space, int(features_dim))
        self.linear = nn.Linear(size, int(features_dim), bias=False)

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return self.linear(observations)


def _check_condition_branch(observation_space: gym.Space, condition_start: int, condition_size: int,
                            hidden: int, name: str) -> tuple[int, slice]:
    """Validate a condition branch's arguments; returns the observation size D and the
    condition slice."""
    if not isinstance(observation_space, gym.spaces.Box) or len(observation_space.shape) != 1:
        raise ValueError(f"observation_space: {name} needs a flat Box, got {observation_space}")
    size = int(observation_space.shape[0])
    stop = int(condition_start) + int(condition_size)
    if not (0 <= int(condition_start) and int(condition_size) > 0 and stop <= size):
        raise ValueError(f"condition_start, condition_size: the slice [{condition_start}, {stop}) must lie in "
                         f"the observation of {size} values")
    if int(hidden) <= 0:
        raise ValueError(f"hidden: must be a positive width, got {hidden}")
    return size, slice(int(condition_start), stop)


class ConditionResidual(BaseFeaturesExtractor):
    """The observation plus a learned function of its condition slice, added everywhere:
    ``features = obs + W2 tanh(LayerNorm(W1 cond))``.

    BehaviorBench gives the reward condition an encoder branch of its own (Linear, LayerNorm,
    Linear, width 64) instead of 10 of ~700 flat inputs. A trained flat policy converts with
    the branch's output layer at zero (:func:`add_condition_branch`), so it computes what it
    did, and PPO can then grow how much the style moves the features. (In a fresh SB3 policy
    ``ortho_init`` re-initialises that layer like every other.)

    Args:
        observation_space: flat Box of D values.
        condition_start: index of the first condition value in the observation
            (:class:`cpsim.observation.ObsLayout` ``.condition.start``: 17).
        condition_size: number of condition values (10).
        hidden: width of the branch.
    Shapes:
        forward: (B, D) float -> (B, D).
    """

    def __init__(self, observation_space: gym.Space, condition_start: int = 17, condition_size: int = 10,
                 hidden: int = 64) -> None:
        size, condition = _check_condition_branch(observation_space, condition_start, condition_size, hidden,
                                                  "ConditionResidual")
        super().__init__(observation_space, size)
        self.condition = condition
        self.branch = nn.Sequential(nn.Linear(int(condition_size), int(hidden)), nn.LayerNorm(int(hidden)),
                                    nn.Tanh(), nn.Linear(int(hidden), size))
        nn.init.zeros_(self.branch[-1].weight)
        nn.init.zeros_(self.branch[-1].bias)

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return observations + self.branch(observations[..., self.condition])


class ConditionConcat(BaseFeaturesExtractor):
    """The observation with a learned encoding of its condition slice appended:
    ``features = [obs, tanh(LayerNorm(W1 cond))]`` ((B, D + hidden)).

    Unlike :class:`ConditionResidual` it leaves every observation value as it is (the zero
    rows that mean "no partner / no road segment here" stay zero); the layers after it read
    the style from ``hidden`` extra inputs. A trained flat policy converts with zero weights
    on those inputs (:func:`add_condition_branch`), so it computes what it did.

    Args:
        observation_space: flat Box of D values.
        condition_start, condition_size, hidden: as :class:`ConditionResidual`.
    Shapes:
        forward: (B, D) float -> (B, D + hidden).
    """

    def __init__(self, observation_space: gym.Space, condition_start: int = 17, condition_size: int = 10,
                 hidden: int = 64) -> None:
        size, condition = _check_condition_branch(observation_space, condition_start, condition_size, hidden,
                                                  "ConditionConcat")
        super().__init__(observation_space, size + int(hidden))
        self.condition = condition
        self.branch = nn.Sequential(nn.Linear(int(condition_size), int(hidden)), nn.LayerNorm(int(hidden)),
                                    nn.Tanh())

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return th.cat([observations, self.branch(observations[..., self.condition])], dim=-1)


def add_condition_branch(source: nn.Module, target: nn.Module) -> list[str]:
    """Copy a flat recurrent policy into one whose features extractor is a
    :class:`ConditionResidual` or a :class:`ConditionConcat`, in place, so that both compute
    the same: every parameter of ``source`` goes to the same name in ``target``; a residual
    branch's output layer is zeroed, and with a concatenated branch the layers that read the
    features (:func:`input_weight_rows`) get zero weights on the appended inputs.

    Returns:
        The names of the target's parameters that were not copied (the branch's).
    Raises:
        ValueError: a target without a condition branch, or a source parameter the target
        lacks or holds in another shape.
    """
    extractor = getattr(target, "features_extractor", None)
    if not isinstance(extractor, (ConditionResidual, ConditionConcat)):
        raise ValueError("target: its policy_kwargs need features_extractor_class=ConditionResidual or "
                         "ConditionConcat")
    widened = {name for name, _ in input_weight_rows(target)} if isinstance(extractor, ConditionConcat) else set()
    src = source.state_dict()
    dst = target.state_dict()
    for name, value in src.items():
        fits = name in dst and (dst[name].shape == value.shape or (
            name in widened and dst[name].shape[0] == value.shape[0] and dst[name].shape[1] > value.shape[1]))
        if not fits:
            got = None if name not in dst else tuple(dst[name].shape)
            raise ValueError(f"source: parameter {name} {tuple(value.shape)} has no match in the target ({got})")
    params = dict(target.named_parameters())
    with th.no_grad():
        for name, value in src.items():
            if name in widened:
                params[name].zero_()
                params[name][:, : value.shape[1]] = value
        target.load_state_dict({k: v for k, v in src.items() if k not in widened}, strict=False)
        if isinstance(extractor, ConditionResidual):
            # SB3's ortho_init re-initialises every features-extractor layer after construction
            extractor.branch[-1].weight.zero_()
            extractor.branch[-1].bias.zero_()
    return sorted(set(dst) - set(src))


#: The features extractors a recipe's ``policy_kwargs`` string may name (rl-zoo3 style).
FEATURE_EXTRACTORS: dict[str, type[BaseFeaturesExtractor]] = {
    "LinearEncoder": LinearEncoder, "ConditionResidual": ConditionResidual, "ConditionConcat": ConditionConcat}


def encoder_policy_kwargs(policy_kwargs: dict[str, Any] | None, features_dim: int) -> dict[str, Any]:
    """``policy_kwargs`` with a :class:`LinearEncoder` of ``features_dim`` in front of the LSTM."""
    out = dict(policy_kwargs or {})
    out["features_extractor_class"] = LinearEncoder
    out["features_extractor_kwargs"] = {"features_dim": int(features_dim)}
    return out


def input_weight_rows(policy: nn.Module) -> list[tuple[str, th.Tensor]]:
    """The weights that read the features directly, each (rows, features_dim): the actor
    LSTM's ``weight_ih_l0``, the critic LSTM's or the critic's linear layer when present."""
    rows: list[tuple[str, th.Tensor]] = [("lstm_actor.weight_ih_l0", policy.lstm_actor.weight_ih_l0)]
    if getattr(policy, "lstm_critic", None) is not None:
        rows.append(("lstm_critic.weight_ih_l0", policy.lstm_critic.weight_ih_l0))
    elif isinstance(getattr(policy, "critic", None), nn.Linear):
        rows.append(("critic.weight", policy.critic.weight))
    return rows


def factorize_input_layers(source: nn.Module, target: nn.Module, observations: np.ndarray,
                           critic_weight: float = 0.5) -> dict[str, float]:
    """Copy a flat recurrent policy into one with a :class:`LinearEncoder`, in place.

    Every parameter that exists in both with the same shape is copied. The input layers
    ``W`` (stacked rows of :func:`input_weight_rows`, (R, D)) are replaced by ``U @ E`` with
    ``E`` (r, D) the encoder and ``U`` (R, r) the new input weights, chosen to minimise
    ``|| X W^T - X E^T U^T ||`` over the given observations (reduced-rank regression: the
    top r right singular vectors of ``X W^T``). The critic's rows count ``critic_weight``
    times as much as the actor's in that fit.

    Args:
        source: policy with the flat features extractor (trained).
        target: same architecture but ``features_extractor_class=LinearEncoder`` (rank r);
            modified in place.
        observations: (N, D) float, observations the policy sees (live agents), N >= r.
        critic_weight: relative weight of the critic's rows in the fit, > 0.
    Returns:
        ``{"rank": r, "relative_error": ||XW^T - X E^T U^T||^2 / ||XW^T||^2, "actor_relative_error": ...}``
        (squared norms, unweighted, on the given observations; the input projections only,
        not the recurrent term or the biases).
    Raises:
        ValueError: a target without a shared LinearEncoder, a rank above the stacked rows,
        a source that is not flat or differs from the target elsewhere, bad observations.
    """
    encoder = getattr(target, "features_extractor", None)
    if not isinstance(encoder, LinearEncoder):
        raise ValueError("target: its policy_kwargs need features_extractor_class=LinearEncoder")
    if not getattr(target, "share_features_extractor", True):
        raise ValueError("target: share_features_extractor=False is not supported (one encoder feeds the "
                         "actor and the critic)")
    if not (np.isfinite(critic_weight) and critic_weight > 0):
        raise ValueError(f"critic_weight: must be a finite number > 0, got {critic_weight}")
    x = np.asarray(observations, dtype=np.float64)
    rank = encoder.features_dim
    size = encoder.linear.in_features
    if x.ndim != 2 or x.shape[1] != size:
        raise ValueError(f"observations: expected (N, {size}), got {x.shape}")
    if x.shape[0] < rank:
        raise ValueError(f"observations: need at least {rank} rows (the rank), got {x.shape[0]}")
    if not np.isfinite(x).all():
        raise ValueError("observations: contain NaN or infinite values")
    src_rows = input_weight_rows(source)
    tgt_rows = input_weight_rows(target)
    if [n for n, _ in src_rows] != [n for n, _ in tgt_rows]:
        raise ValueError(f"source and target differ in their input layers: {[n for n, _ in src_rows]} "
                         f"vs {[n for n, _ in tgt_rows]}")
    if any(w.shape[1] != size for _, w in src_rows):
        raise ValueError(f"source: its input layers must read the {size}-wide observation directly (a flat "
                         "features extractor)")
    n_rows = sum(w.shape[0] for _, w in src_rows)
    if rank > n_rows:
        raise ValueError(f"target: features_dim {rank} exceeds the {n_rows} input rows it factorises")
    src_state = source.state_dict()
    replaced = {name for name, _ in tgt_rows} | {"features_extractor.linear.weight"}
    for name, value in target.state_dict().items():
        if name in replaced or name.startswith(("pi_features_extractor.", "vf_features_extractor.")):
            continue
        if name not in src_state or src_state[name].shape != value.shape:
            got = None if name not in src_state else tuple(src_state[name].shape)
            raise ValueError(f"source and target differ outside the input layers: {name} is {got} in the "
                             f"source, {tuple(value.shape)} in the target")
    weights = [w.detach().double().cpu().numpy() for _, w in src_rows]
    scale = np.concatenate([np.full(w.shape[0], 1.0 if i == 0 else np.sqrt(critic_weight))
                            for i, w in enumerate(weights)])
    stacked = np.concatenate(weights, axis=0)  # (R, D)
    response = (x @ stacked.T) * scale  # (N, R)
    _, _, vt = np.linalg.svd(response, full_matrices=False)
    basis = vt[:rank] / scale  # (r, R): undo the weighting on the way back
    projector = vt[:rank]  # orthonormal rows in the weighted space
    encoder_weight = projector @ (stacked * scale[:, None])  # (r, D)
    new_rows = basis.T  # (R, r)  (stacked ~= new_rows @ encoder_weight)

    with th.no_grad():
        for name, value in target.state_dict().items():
            if name in replaced or name.startswith(("pi_features_extractor.", "vf_features_extractor.")):
                continue
            value.copy_(src_state[name])
        encoder.linear.weight.copy_(th.as_tensor(encoder_weight, dtype=encoder.linear.weight.dtype))
        start = 0
        for _, param in tgt_rows:
            n = param.shape[0]
            param.copy_(th.as_tensor(new_rows[start:start + n], dtype=param.dtype))
            start += n
    fitted = x @ encoder_weight.T @ new_rows.T
    exact = x @ stacked.T
    actor = slice(0, weights[0].shape[0])
    return {
        "rank": int(rank),
        "relative_error": float(np.sum((exact - fitted) ** 2) / max(np.sum(exact ** 2), 1e-300)),
        "actor_relative_error": float(np.sum((exact[:, actor] - fitted[:, actor]) ** 2)
                                      / max(np.sum(exact[:, actor] ** 2), 1e-300)),
    }
