"""Learnt traffic: the behaviour-cloning co-player model of the ``bc`` evaluation regime.

* :mod:`~cpalgo.traffic.bc`: the model (:class:`BCPolicy`, a ``.pt`` file), its data
  (log-replay labels, DAgger against the tracking expert) and its training.
* :mod:`~cpalgo.traffic.measure`: the expert-replay ego under each model's traffic
  (:func:`measure_traffic`, through the evaluator).
* :mod:`~cpalgo.traffic.cli`: ``python -m cpalgo.traffic`` (also ``python -m cpalgo.bc``).

Names load on first use (torch is imported then).
"""

from __future__ import annotations

from cpsim._lazy import lazy_exports

_BC = "cpalgo.traffic.bc"
_LAZY = {name: _BC for name in ("BCPolicy", "BCData", "TrainConfig", "DaggerConfig", "RolloutStats", "collect",
                                "train", "dagger", "aggregate", "traffic_rollouts", "labelled_steps",
                                "targets_to_logits", "targets_to_actions")}
_LAZY["measure_traffic"] = "cpalgo.traffic.measure"
__getattr__, __dir__ = lazy_exports("cpalgo.traffic", _LAZY, globals())
__all__ = list(_LAZY)
