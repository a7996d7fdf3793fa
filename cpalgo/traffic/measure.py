"""How a traffic model treats the ego: the expert-replay ego under ``bc`` traffic driven
by each model, measured with the evaluator (:mod:`cpalgo.evaluate.runner`) on the same
tasks. The evaluator loads a ``.pt`` model through :mod:`cpalgo.traffic.bc`, which imports
nothing of the evaluator, so the two do not import each other."""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from cpalgo.evaluate.runner import EvalConfig, Evaluator, make_tasks
from cpalgo.traffic.bc import BCPolicy

__all__ = ["measure_traffic"]


class _Switch:
    """A co-player model that forwards to whichever model is current (one evaluator, and
    so one road-grid build, serves every model measured)."""

    def __init__(self) -> None:
        self.model: Any = None

    @property
    def obs_size(self) -> int | None:
        return getattr(self.model, "obs_size", None)

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        return self.model.predict(observation, state, episode_start, deterministic)


def measure_traffic(models: dict[str, Any], pool: str | os.PathLike = "procedural", n: int = 50, seed: int = 0,
                    split: str = "both", max_worlds: int = 256) -> dict[str, dict[str, float]]:
    """The expert-replay ego under ``bc`` traffic driven by each model, on the same tasks.

    ``models``: label -> BC model (or ``.pt`` path); the log-replay regime on the same
    tasks is added as ``replay``. Tasks: :func:`cpalgo.evaluate.runner.make_tasks`
    (``pool``, ``split``, ``n``, ``seed``). Returns label -> ``tasks``, ``co_player_harm``
    (other vehicles that collided or went off-road, per task), ``at_fault`` (share of
    tasks with an at-fault collision of the ego), ``collision``, ``goal``, ``seconds``.
    """
    if not models:
        raise ValueError("models: nothing to measure")
    tasks = make_tasks(pool, split, n, seed=seed)
    switch = _Switch()
    ev = Evaluator(tasks, ["bc", "replay"], bc_policy=switch,
                   config=EvalConfig(progress=False, seed=seed, max_worlds=max_worlds))
    out: dict[str, dict[str, float]] = {}
    for k, (label, model) in enumerate(models.items()):
        t0 = time.perf_counter()
        switch.model = BCPolicy.load(model) if isinstance(model, (str, os.PathLike)) else model
        c = ev.run("expert").columns
        for regime, name in (("bc", label), ("replay", "replay")):
            if regime == "replay" and k > 0:
                continue
            m = c["regime"] == regime
            out[name] = {"tasks": int(m.sum()), "co_player_harm": float(c["co_player_harm"][m].mean()),
                         "at_fault": float(c["at_fault_collision"][m].mean()),
                         "collision": float((c["at_fault_collision"] | c["non_at_fault_collision"])[m].mean()),
                         "goal": float(c["goal"][m].mean()), "seconds": time.perf_counter() - t0}
    return out
