"""Does the critic know the task? Its value along failed self-play episodes.

CounterPlay's value-guided root rule backtracks from a failure to the latest root whose
focal value is still high. That only works when the critic's value *falls* as an episode
heads into a failure; a critic that prices the style penalties still to pay lets it rise
instead. :func:`value_before_failures` runs one self-play episode per held-out task with
the policy's own sampled actions (as the searches see the anchor) and reports, over the
agents that fail (collision, off-road or timeout), the share whose value at the failure is
below their value ``horizon`` decisions (2 s) earlier.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np
import torch as th

from cpalgo.common.policy_utils import put_states, take_states
from cpsim.conditions import NUM_CONDITION_FIELDS, deployment_condition
from cpsim.config import Controller, Outcome, SimConfig
from cpsim.simulator import Simulator

__all__ = ["ValueTrend", "value_before_failures"]


@dataclasses.dataclass(frozen=True)
class ValueTrend:
    """Failed agents, the share whose value fell over the ``horizon`` decisions before the
    failure, and the mean change (value at failure minus value ``horizon`` before), overall
    and per failure class."""

    horizon: int
    failures: int
    falls: float
    mean_change: float
    per_outcome: dict[str, dict[str, float]]

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def value_before_failures(model: Any, scenarios: Sequence[Any], condition: Any = "normal", max_agents: int = 8,
                          horizon: int = 20, config: Any = None, deterministic: bool = False,
                          seed: int = 0) -> ValueTrend:
    """Value of every failed POLICY agent at its failure vs ``horizon`` decisions before.

    Args:
        model: a recurrent SB3 model (``model.policy`` a recurrent actor-critic).
        scenarios: held-out tasks, one world each, every controllable agent driven by the
            policy under ``condition`` (style fields; the goal test is the evaluation's).
        horizon: decisions back (20 = 2 s); agents failing earlier than that are skipped.
        deterministic: argmax actions (default: sampled, as self-play and the searches).
    Returns:
        :class:`ValueTrend` over the failures (the value at a failure is the critic's value
        of the last observation before the failing step).
    """
    if horizon < 1:
        raise ValueError(f"horizon: expected >= 1, got {horizon!r}")
    scenarios = list(scenarios)
    if not scenarios:
        raise ValueError("scenarios: empty")
    cond = deployment_condition(condition, "condition")
    config = SimConfig.from_dict(config).replace(goal_criterion="evaluation")
    policy = model.policy
    # sampled actions from a seeded generator state that is restored afterwards: the check
    # neither depends on nor disturbs the caller's torch RNG (a training run's sampling)
    with th.random.fork_rng(devices=[]):
        th.manual_seed(seed)
        return _value_trend(policy, scenarios, cond, config, max_agents, horizon, deterministic, seed)


def _value_trend(policy: Any, scenarios: list[Any], cond: np.ndarray, config: SimConfig, max_agents: int,
                 horizon: int, deterministic: bool, seed: int) -> ValueTrend:
    changes: dict[str, list[float]] = {"collision": [], "offroad": [], "timeout": []}
    names = {int(Outcome.COLLISION): "collision", int(Outcome.OFFROAD): "offroad", int(Outcome.TIMEOUT): "timeout"}
    sim = Simulator(scenarios, num_worlds=len(scenarios), max_agents=max_agents, config=config, seed=seed)
    W, A = sim.num_worlds, sim.max_agents
    sim.reset(scenario_index=np.arange(W), conditions=np.broadcast_to(cond, (W, A, NUM_CONDITION_FIELDS)))
    task = ((sim.controllers == int(Controller.POLICY)) & sim.alive).reshape(-1).cpu().numpy()
    T = sim.config.episode_steps
    values = np.full((T, W * A), np.nan, np.float32)
    lstm = policy.lstm_actor
    zeros = th.zeros((lstm.num_layers, W * A, lstm.hidden_size))
    from sb3_contrib.common.recurrent.type_aliases import RNNStates

    states = RNNStates((zeros, zeros.clone()), (zeros.clone(), zeros.clone()))
    starts = th.ones(W * A)
    ended_at = np.full(W * A, -1)
    for t in range(T):
        live = (sim.policy_mask.reshape(-1).cpu().numpy()).copy()
        idx = th.as_tensor(np.flatnonzero(live))
        actions = th.zeros(W * A, dtype=th.int32)
        if idx.numel():  # the policy runs on the live slots only (rows are independent)
            obs = th.as_tensor(sim.obs.reshape(W * A, -1).cpu().numpy()[live])
            with th.no_grad():
                act, vals, _, part = policy(obs, take_states(states, idx), starts[idx], deterministic=deterministic)
            states = put_states(states, idx, part)
            actions[idx] = act.reshape(-1).to(th.int32)
            values[t, live] = vals.reshape(-1).numpy()
        starts = th.zeros(W * A)
        sim.step(actions.reshape(W, A))
        now_done = live & ~sim.policy_mask.reshape(-1).cpu().numpy()
        ended_at[now_done & (ended_at < 0)] = t
        if bool(sim.world_done.all()):
            break
    outcome = sim.outcome.reshape(-1).cpu().numpy()
    still = ended_at < 0
    ended_at[still] = T - 1
    outcome = np.where(still & (outcome == int(Outcome.RUNNING)), int(Outcome.TIMEOUT), outcome)
    for i in np.flatnonzero(task & np.isin(outcome, list(names))):
        t_end = int(ended_at[i])
        if t_end - horizon < 0 or np.isnan(values[t_end - horizon, i]) or np.isnan(values[t_end, i]):
            continue
        changes[names[int(outcome[i])]].append(float(values[t_end, i] - values[t_end - horizon, i]))
    every = [c for v in changes.values() for c in v]
    per = {k: {"failures": len(v), "falls": float(np.mean(np.array(v) < 0)) if v else float("nan"),
               "mean_change": float(np.mean(v)) if v else float("nan")} for k, v in changes.items()}
    return ValueTrend(horizon=horizon, failures=len(every),
                      falls=float(np.mean(np.array(every) < 0)) if every else float("nan"),
                      mean_change=float(np.mean(every)) if every else float("nan"), per_outcome=per)
