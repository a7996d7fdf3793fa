"""Registers the seed paper's six adapted baselines in the method registry, in the paper's
table order (SPICED, CL4AD, DAPO, VinePPO, PlannerRFT, CRAFT) whichever of their packages
is imported first. Each package's ``__init__`` imports this module; the algorithms are
registered as ``"module:Class"`` strings, so nothing heavy is imported here."""

from __future__ import annotations

from cpalgo.methods import register

__all__ = ["BASELINES"]

_NONE = {"B": "-", "C": "-", "S": "-", "D": "-"}

#: (name, algorithm, row label, summary) in table order
BASELINES: tuple[tuple[str, str, str, str], ...] = (
    ("spiced", "cpalgo.baselines.spiced.spiced:Spiced", "SPICED\u2020",
     "SPICED: PPO + KL toward a frozen BC policy cloned from log-tracking actions"),
    ("cl4ad", "cpalgo.baselines.cl4ad.cl4ad:CL4AD", "CL4AD\u2020",
     "CL4AD: learnability curriculum (scenarios with success near 0.5) instead of uniform sampling"),
    ("dapo", "cpalgo.baselines.dapo.dapo:DAPO", "DAPO\u2020",
     "DAPO: groups of 6 continuations from interaction states, decoupled clip, dynamic sampling"),
    ("vineppo", "cpalgo.baselines.vineppo.vineppo:VinePPO", "VinePPO\u2020",
     "VinePPO: critic value at interaction states replaced by the mean return of 6 continuations"),
    ("plannerrft", "cpalgo.baselines.plannerrft.plannerrft:PlannerRFT", "PlannerRFT\u2020",
     "PlannerRFT: clipped group-relative objective vs log-replayed traffic, learned temperature"),
    ("craft", "cpalgo.baselines.craft.craft:CRAFT", "CRAFT\u2020",
     "CRAFT: score function on 6 continuations, hold/decay traffic proxy + closed-loop residual, EMA KL"),
)

for _name, _algorithm, _label, _summary in BASELINES:
    register(_name, _summary, _algorithm, group="baseline", label=_label, components=_NONE, replace=True)
