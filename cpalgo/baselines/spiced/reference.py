"""SPICED-dagger's frozen reference policy: behaviour cloning of log-tracking actions.

:func:`tracking_reference` drives the training scenarios with
:class:`cpsim.expert.TrackingExpert` (every controllable agent follows its log with the
simulator's own discrete actions, conditions drawn from p_train) and fits a
:class:`cpalgo.traffic.bc.BCPolicy` (an MLP over the observation with the condition slice zeroed:
a human reference knows no reward condition) to the expert's labels by cross-entropy
(:func:`cpalgo.traffic.bc.train`). :func:`load_reference` reads a ``python -m cpalgo.traffic``
checkpoint (the shipped ``zoo/bc_traffic.pt``) and checks that it fits the policy's
observation and action space.

:class:`ReferenceStepper` evaluates a reference on rollout observations: a feed-forward
module (obs -> logits) directly, a recurrent SB3 policy with its own LSTM memory per env
slot (reset at episode starts).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import torch as th
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from sb3_contrib.common.recurrent.type_aliases import RNNStates

from cpalgo.common.policy_utils import policy_step_logits, put_states, take_states, zero_states

__all__ = ["tracking_reference", "load_reference", "ReferenceStepper"]


def tracking_reference(policy: RecurrentActorCriticPolicy, sim: Any, *, num_worlds: int = 16, episodes: int = 2,
                       epochs: int = 10, hidden: int = 128, seed: int = 0) -> tuple[Any, dict[str, float]]:
    """Behaviour-clone :class:`cpsim.expert.TrackingExpert` on ``sim``'s scenarios.

    Args:
        policy: the recurrent policy under training (only read: the episode collector
            reports its agreement with the expert).
        sim: the training simulator (its scenario pool, ``max_agents`` and config are used).
        num_worlds: worlds per collected batch; episodes: batches (each one episode per world).
        epochs: BC epochs; hidden: width of the two hidden layers; seed: draws and init.
    Returns:
        the frozen :class:`cpalgo.traffic.bc.BCPolicy` and its metrics (``cpalgo.traffic.bc.train``'s plus
        ``samples`` and ``expert_agreement``).
    """
    from cpalgo.anchor.imitation import collect_episodes
    from cpalgo.traffic.bc import BCData, TrainConfig, train
    from cpsim.expert import TrackingExpert
    from cpsim.simulator import Simulator

    pool = getattr(sim, "model", None) or sim.scenarios
    probe = Simulator(pool, num_worlds=int(num_worlds), max_agents=int(sim.max_agents), config=sim.config,
                      device="cpu" if str(sim.device) == "cpu" else str(sim.device), seed=int(seed))
    expert = TrackingExpert(probe)
    rng = np.random.default_rng(int(seed))
    obs, labels, scen = [], [], []
    agreement = []
    a = int(probe.max_agents)
    was_training = policy.training
    policy.set_training_mode(False)
    try:
        for _ in range(int(episodes)):
            batch = collect_episodes(policy, probe, expert, beta=1.0, rng=rng)
            mask = batch.mask.numpy()
            world_scenario = probe.world_scenario.cpu().numpy().astype(np.int64)
            obs.append(batch.obs.numpy()[mask])
            labels.append(batch.labels.numpy()[mask])
            scen.append(np.broadcast_to(np.repeat(world_scenario, a)[None], mask.shape)[mask])
            agreement.append(batch.agreement)
    finally:
        policy.set_training_mode(was_training)
    x = np.concatenate(obs).astype(np.float32)
    data = BCData(obs=x, actions=np.concatenate(labels).astype(np.int64), error_m=np.zeros(x.shape[0], np.float32),
                  scenario=np.concatenate(scen))
    sl = probe.obs_layout.condition
    many = np.unique(data.scenario).size > 2
    model, metrics = train(data, int(probe.config.num_actions), (int(sl.start), int(sl.stop)),
                           TrainConfig(hidden=(int(hidden), int(hidden)), epochs=int(epochs), seed=int(seed),
                                       val_fraction=0.15 if many else 0.0))
    for p in model.parameters():
        p.requires_grad_(False)
    metrics.update(samples=int(x.shape[0]), expert_agreement=float(np.mean(agreement)))
    model.meta = dict(metrics, source="tracking")
    return model, metrics


def load_reference(path: str | os.PathLike, obs_size: int, num_actions: int) -> Any:
    """A ``cpalgo.traffic`` checkpoint as the reference; ``ValueError`` naming ``reference`` when
    it does not fit the policy's observation size or action count."""
    from cpalgo.recipes import resolve_path
    from cpalgo.traffic.bc import BCPolicy

    resolved = resolve_path(path)
    if not os.path.isfile(resolved):
        raise ValueError(f"reference: no such behaviour-cloning checkpoint {str(path)!r}")
    try:
        model = BCPolicy.load(resolved)
    except ValueError as exc:
        raise ValueError(f"reference: {exc}") from None
    if model.obs_size != int(obs_size) or model.num_actions != int(num_actions):
        raise ValueError(f"reference: {str(path)!r} has observation size {model.obs_size} and {model.num_actions} "
                         f"actions; the policy has {obs_size} and {num_actions}")
    for p in model.parameters():
        p.requires_grad_(False)
    return model


class ReferenceStepper:
    """Reference logits on rollout decisions (no gradients).

    Args:
        reference: a module ``obs (n, D) -> logits (n, n_actions)`` or a recurrent SB3
            policy (then every slot keeps its own memory of the reference).
        num_envs: env slots N; device: where inputs live.
    """

    def __init__(self, reference: Any, num_envs: int, device: th.device | str) -> None:
        self.reference = reference
        self.recurrent = isinstance(reference, RecurrentActorCriticPolicy)
        self.device = th.device(device)
        self.states: RNNStates | None = zero_states(reference, int(num_envs), self.device) if self.recurrent else None

    @th.no_grad()
    def step(self, obs: th.Tensor, episode_starts: th.Tensor, index: th.Tensor | None) -> th.Tensor:
        """Logits of the slots ``index`` (None: every slot) for this decision.

        Args:
            obs: (N, D); episode_starts: (N,) float; index: (k,) slot indices.
        Returns:
            (k, n_actions) float32 logits (k = N when ``index`` is None).
        """
        sel = index if index is not None else th.arange(obs.shape[0], device=obs.device)
        if not self.recurrent:
            return self.reference(obs[sel].float()).float()
        assert self.states is not None
        logits, _, new = policy_step_logits(self.reference, obs[sel], take_states(self.states, sel),
                                            episode_starts[sel])
        self.states = put_states(self.states, sel, new)
        return logits.float()
