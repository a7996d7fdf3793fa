"""The held-out procedural tasks the commands report on, and self-play outcome rates on them.

``counterplay train-anchor``, ``post-train`` and ``outcomes`` (and ``python -m cpalgo.bench``)
evaluate on the first ``n`` tasks of :func:`cpsim.scenario.eval_pool` at
:data:`HELD_OUT_SEED`: the evaluation seed range, disjoint from training by seed. The tasks
are generated once per process, so an evaluation before and after training shares them.
"""

from __future__ import annotations

import functools
from typing import Any

__all__ = ["HELD_OUT_SEED", "held_out_tasks", "held_out_outcomes"]

#: Held-out tasks come from the evaluation seed range (disjoint from training by seed).
HELD_OUT_SEED = 0


@functools.lru_cache(maxsize=4)
def held_out_tasks(n: int) -> tuple:
    """The first ``n`` held-out tasks (generated once per process: before and after share them)."""
    from cpsim.scenario import eval_pool

    return tuple(eval_pool(n, seed=HELD_OUT_SEED))


def held_out_outcomes(model: Any, n_tasks: int, max_agents: int, condition: Any = "normal") -> Any:
    """Self-play outcome rates of ``model`` on the first ``n_tasks`` held-out tasks, every
    controllable agent under ``condition`` (:func:`cpalgo.anchor.outcomes.selfplay_outcomes`),
    in the dynamics the model acts in (its action set, :func:`cpalgo.evaluate.runner.policy_dynamics`)."""
    from cpalgo.anchor.outcomes import selfplay_outcomes
    from cpalgo.evaluate.runner import policy_dynamics

    dynamics = policy_dynamics(model, "model")
    return selfplay_outcomes(model, held_out_tasks(n_tasks), condition=condition, max_agents=max_agents,
                             config=None if dynamics is None else {"dynamics": dynamics})
