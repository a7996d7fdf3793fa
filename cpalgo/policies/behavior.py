"""BehaviorBench's conditioned network shape, on this simulator's observation layout.

BehaviorBench's ``DriveConditioned`` (635.6k parameters) encodes four groups of the
observation in branches of Linear -> LayerNorm -> Linear, max-pools the partner and road
branches over their slots, and feeds the concatenation through GELU -> Linear -> ReLU into an
LSTM whose output both the actor (one categorical over the classic 91 actions) and the critic
read. Here the groups are the slices of :class:`cpsim.observation.ObsLayout` (one
observation format), and the widths are set for two CPU cores: the per-slot partner and
road branches cost most of a training pass, and at width 16 instead of 32 the encoder's
forward and backward take 0.08 s instead of 0.21 s per 6,000 transitions (2 cores, measured
with ``python -m cpalgo.bench --recipes``'s network; learning per second was not compared):

==================  =============================  ====================================
part                BehaviorBench                  :class:`BehaviorLstmPolicy` default
==================  =============================  ====================================
ego branch          7 -> 64 -> LN -> 64             17 -> 64 -> LN -> 64
condition branch    10 -> 64 -> LN -> 64            10 -> 32 -> LN -> 32
partner branch      31 x (8 -> 64 -> LN -> 64), max 16 x (10 -> 16 -> LN -> 16), max
road branch         128 x (7 -> 64 -> LN -> 64), max 64 x (8 -> 16 -> LN -> 16), max
trunk               GELU, 256 -> 256, ReLU          GELU, 128 -> 128, ReLU
LSTM                256                             128
heads               actor 256 -> 91, critic 256 -> 1 actor 128 -> 91, critic 128 -> 1
==================  =============================  ====================================

Unlike sb3-contrib's ``shared_lstm`` (which detaches the critic from the LSTM), the critic's
gradient trains the shared LSTM and encoder, as in BehaviorBench: a critic that reads the
memory can tell how a task is going, which the value-guided root rule depends on.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import torch as th
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from sb3_contrib.common.recurrent.type_aliases import RNNStates
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from cpalgo.policies.fused import FusedLstmMixin
from cpsim.observation import ObsLayout

__all__ = ["BehaviorEncoder", "BehaviorLstmPolicy", "branch"]


def branch(d_in: int, width: int) -> nn.Sequential:
    """Linear(d_in, width) -> LayerNorm(width) -> Linear(width, width)."""
    return nn.Sequential(nn.Linear(d_in, width), nn.LayerNorm(width), nn.Linear(width, width))


class BehaviorEncoder(BaseFeaturesExtractor):
    """Ego, condition, partner and road branches, max-pooled, then GELU -> Linear -> ReLU.

    Input (..., D) with D = ``ObsLayout(num_partners, num_road).size``; output (...,
    ``features_dim``). Partner and road slots are pooled with their zero padding, as in
    BehaviorBench (an empty slot's embedding is one constant vector the max learns around).

    Args:
        num_partners, num_road: K and M of the simulator's observation (SimConfig's
            ``num_partners`` / ``num_road``; defaults 16 / 64).
        ego_width, condition_width, partner_width, road_width: branch widths.
        features_dim: trunk output (the LSTM's input).
    """

    def __init__(self, observation_space: gym.Space, num_partners: int = 16, num_road: int = 64,
                 ego_width: int = 64, condition_width: int = 32, partner_width: int = 16, road_width: int = 16,
                 features_dim: int = 128) -> None:
        super().__init__(observation_space, features_dim)
        layout = ObsLayout(num_partners=int(num_partners), num_road=int(num_road))
        size = int(observation_space.shape[-1])
        if size != layout.size:
            raise ValueError(f"observation_space: {size} values do not match num_partners={num_partners}, "
                             f"num_road={num_road} (expected {layout.size}); pass the simulator's K and M in "
                             "features_extractor_kwargs")
        for name, v in (("ego_width", ego_width), ("condition_width", condition_width),
                        ("partner_width", partner_width), ("road_width", road_width),
                        ("features_dim", features_dim)):
            if int(v) < 1:
                raise ValueError(f"{name}: must be >= 1, got {v!r}")
        self.layout = layout
        self.ego = branch(layout.ego_features, ego_width)
        self.condition = branch(layout.condition_features, condition_width)
        self.partners = branch(layout.partner_features, partner_width)
        self.road = branch(layout.road_features, road_width)
        width = ego_width + condition_width + partner_width + road_width
        self.trunk = nn.Sequential(nn.GELU(), nn.Linear(width, features_dim), nn.ReLU())

    def forward(self, observations: th.Tensor) -> th.Tensor:
        parts = self.layout.split(observations)
        partners = self.partners(parts["partners"]).max(dim=-2).values
        road = self.road(parts["road"]).max(dim=-2).values
        joined = th.cat([self.ego(parts["ego"]), self.condition(parts["condition"]), partners, road], dim=-1)
        return self.trunk(joined)


class BehaviorLstmPolicy(FusedLstmMixin, RecurrentActorCriticPolicy):
    """BehaviorBench's network as an sb3-contrib recurrent policy (fused sequence LSTM).

    Defaults: :class:`BehaviorEncoder` features, one LSTM (``lstm_hidden_size`` 128) shared
    by actor and critic with the critic's gradient flowing into it, linear heads on the LSTM
    output (``net_arch=[]``). Every sb3-contrib argument can be overridden; ``shared_lstm``
    and ``enable_critic_lstm`` are fixed by the shape.
    """

    def __init__(self, observation_space: gym.Space, action_space: gym.Space, lr_schedule: Any, **kwargs: Any):
        for fixed in ("shared_lstm", "enable_critic_lstm"):
            if fixed in kwargs:
                raise ValueError(f"policy_kwargs: {fixed!r} is fixed by BehaviorLstmPolicy (one LSTM shared by "
                                 "actor and critic)")
        kwargs.setdefault("features_extractor_class", BehaviorEncoder)
        kwargs.setdefault("lstm_hidden_size", 128)
        kwargs.setdefault("net_arch", [])
        super().__init__(observation_space, action_space, lr_schedule, shared_lstm=True, enable_critic_lstm=False,
                         **kwargs)

    def _features(self, obs: th.Tensor, n_seq: int) -> th.Tensor:
        """The encoder's output for every row; inside :func:`cpalgo.policies.sequence_lengths`
        (PPO minibatches of padded sequences) it runs on the counted rows only and the
        padding after each sequence gets zeros, which the fused LSTM skips and every loss
        masks out (sb3-contrib pads sequences to the longest: 1.1-1.8x the counted rows)."""
        lengths = self._sequence_lengths
        rows = obs.shape[0]
        if lengths is None or lengths.numel() != n_seq or rows % n_seq or rows == n_seq:
            return self.extract_features(obs)
        seq_len = rows // n_seq
        counted = (th.arange(seq_len)[None, :] < lengths[:, None]).reshape(-1).to(obs.device)
        if bool(counted.all()):
            return self.extract_features(obs)
        features = obs.new_zeros((rows, self.features_dim))
        features[counted] = self.extract_features(obs[counted])
        return features

    def _latent(self, obs: th.Tensor, lstm_states: tuple[th.Tensor, th.Tensor], episode_starts: th.Tensor
                ) -> tuple[th.Tensor, th.Tensor, tuple[th.Tensor, th.Tensor]]:
        features = self._features(obs, lstm_states[0].shape[1])
        latent, states = self._process_sequence(features, lstm_states, episode_starts, self.lstm_actor)
        return self.mlp_extractor.forward_actor(latent), self.mlp_extractor.forward_critic(latent), states

    def forward(self, obs: th.Tensor, lstm_states: RNNStates, episode_starts: th.Tensor,
                deterministic: bool = False) -> tuple[th.Tensor, th.Tensor, th.Tensor, RNNStates]:
        latent_pi, latent_vf, states = self._latent(obs, lstm_states.pi, episode_starts)
        values = self.value_net(latent_vf)
        distribution = self._get_action_dist_from_latent(latent_pi)
        actions = distribution.get_actions(deterministic=deterministic)
        log_prob = distribution.log_prob(actions)
        actions = actions.reshape((-1, *self.action_space.shape))
        # the critic's state is the actor's: one LSTM (kept as two entries for RNNStates)
        return actions, values, log_prob, RNNStates(states, states)

    def evaluate_actions(self, obs: th.Tensor, actions: th.Tensor, lstm_states: RNNStates,
                         episode_starts: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        latent_pi, latent_vf, _ = self._latent(obs, lstm_states.pi, episode_starts)
        distribution = self._get_action_dist_from_latent(latent_pi)
        return self.value_net(latent_vf), distribution.log_prob(actions), distribution.entropy()
