"""Self-play outcome rates of a policy on held-out tasks (the anchor's report card).

Every controllable agent of every task is driven by the same policy under one fixed
condition (default: the normal profile), every other agent follows its log, one episode
per task, all tasks batched as worlds of one :class:`cpsim.Simulator`.

The goal test is the evaluation criterion (:data:`cpsim.config.EVAL_GOAL`, 2 m and no
effective speed limit) whatever the condition: the condition supplies the style fields
only (:func:`cpsim.conditions.deployment_condition`), so rates under different profiles
measure the same task.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import numpy as np
import torch

from cpsim.conditions import NUM_CONDITION_FIELDS, deployment_condition
from cpsim.config import Controller, Outcome, SimConfig
from cpsim.scenario import Scenario
from cpsim.simulator import Simulator


@dataclasses.dataclass(frozen=True)
class OutcomeRates:
    """Shares of POLICY agents ending in each outcome (they sum to 1), and the count."""

    goal: float
    collision: float
    offroad: float
    timeout: float
    agents: int
    tasks: int

    def as_dict(self) -> dict[str, float | int]:
        return dataclasses.asdict(self)

    def __str__(self) -> str:
        return (f"goal {self.goal:.1%}  collision {self.collision:.1%}  off-road {self.offroad:.1%}  "
                f"timeout {self.timeout:.1%}  ({self.agents} agents, {self.tasks} tasks)")


def selfplay_outcomes(model: Any, scenarios: Sequence[Scenario], condition: Any = "normal",
                      max_agents: int = 8, deterministic: bool = True, config: Any = None,
                      chunk: int = 256, seed: int = 0) -> OutcomeRates:
    """Run one self-play episode per scenario with ``model`` and count POLICY outcomes.

    Args:
        model: an SB3 model (recurrent or not) trained on ``SelfPlayVecEnv`` observations.
        scenarios: the held-out tasks (one world each).
        condition: profile name or raw 10-vector whose style fields every policy agent
            gets; the task fields and the goal test are the evaluation criterion's.
        max_agents: agent slots per world (must match the model's training only in that
            the observation layout is the same; slot count is free).
        deterministic: argmax actions.
        config: SimConfig (or dict) of the simulator; default SimConfig(). Its
            ``goal_criterion`` is set to "evaluation".
        chunk: worlds per simulator batch.
    """
    def drive(sim: Simulator) -> None:
        obs_size = sim.obs_layout.size
        if model.observation_space.shape != (obs_size,):
            raise ValueError(
                f"model: observation shape {model.observation_space.shape} does not match the "
                f"simulator's ({obs_size},)"
            )
        W, A = sim.num_worlds, sim.max_agents
        state = None
        starts = np.ones(W * A, bool)
        for _ in range(sim.config.episode_steps):
            # the policy runs on the live slots only (rows are independent; the rest act 0)
            live = np.flatnonzero(sim.policy_mask.reshape(-1).cpu().numpy())
            actions = np.zeros(W * A, np.int64)
            if live.size:
                obs = sim.obs.reshape(W * A, -1).cpu().numpy()[live]
                sub = None if state is None else tuple(s[:, live] for s in state)
                act, new = model.predict(obs, state=sub, episode_start=starts[live], deterministic=deterministic)
                actions[live] = np.asarray(act).reshape(-1)
                if new is not None:
                    if state is None:
                        state = tuple(np.zeros((s.shape[0], W * A, *s.shape[2:]), s.dtype) for s in new)
                    for full, part in zip(state, new):
                        full[:, live] = part
            starts[:] = False
            sim.step(torch.as_tensor(actions.reshape(W, A), dtype=torch.int32))
            if bool(sim.world_done.all()):
                break

    return _episode_outcomes(drive, scenarios, condition, max_agents, config, chunk, seed)


def expert_outcomes(scenarios: Sequence[Scenario], condition: Any = "normal", max_agents: int = 8,
                    config: Any = None, chunk: int = 256, seed: int = 0, teacher: str = "tracking") -> OutcomeRates:
    """As :func:`selfplay_outcomes`, with every POLICY agent driven by the imitation teacher
    ``teacher`` (:func:`cpsim.expert.make_expert`: "tracking" or "reactive"; an upper reference)."""
    from cpsim.expert import EXPERTS, make_expert

    if teacher not in EXPERTS:  # before any simulator is built
        raise ValueError(f"teacher: unknown expert {teacher!r}; accepted: {list(EXPERTS)}")

    def drive(sim: Simulator) -> None:
        expert = make_expert(teacher, sim)
        for _ in range(sim.config.episode_steps):
            sim.step(expert.actions())
            if bool(sim.world_done.all()):
                break

    return _episode_outcomes(drive, scenarios, condition, max_agents, config, chunk, seed)


def _episode_outcomes(drive: Callable[[Simulator], None], scenarios: Sequence[Scenario], condition: Any,
                      max_agents: int, config: Any, chunk: int, seed: int) -> OutcomeRates:
    """One episode per scenario, ``chunk`` worlds per simulator, every policy agent under
    ``condition``; ``drive(sim)`` runs the episode from the reset; POLICY outcomes counted."""
    scenarios = list(scenarios)
    if not scenarios:
        raise ValueError("scenarios: empty")
    cond = deployment_condition(condition, "condition")
    config = SimConfig.from_dict(config).replace(goal_criterion="evaluation")
    counts = np.zeros(len(Outcome), np.int64)
    for start in range(0, len(scenarios), chunk):
        part = scenarios[start:start + chunk]
        sim = Simulator(part, num_worlds=len(part), max_agents=max_agents, config=config, seed=seed)
        W, A = sim.num_worlds, sim.max_agents
        sim.reset(scenario_index=np.arange(W),
                  conditions=np.broadcast_to(cond, (W, A, NUM_CONDITION_FIELDS)))
        policy_agents = (sim.controllers == int(Controller.POLICY)) & sim.alive
        drive(sim)
        counts += np.bincount(sim.outcome[policy_agents].cpu().numpy(), minlength=len(Outcome))
    return _rates(counts, len(scenarios))


def _rates(counts: np.ndarray, tasks: int) -> OutcomeRates:
    counts = counts.copy()
    # an agent still running when the episode ended has timed out
    counts[int(Outcome.TIMEOUT)] += counts[int(Outcome.RUNNING)]
    total = max(int(counts[1:].sum()), 1)
    return OutcomeRates(
        goal=counts[int(Outcome.GOAL)] / total,
        collision=counts[int(Outcome.COLLISION)] / total,
        offroad=counts[int(Outcome.OFFROAD)] / total,
        timeout=counts[int(Outcome.TIMEOUT)] / total,
        agents=int(counts[1:].sum()),
        tasks=tasks,
    )
