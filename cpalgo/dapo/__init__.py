"""DAPO-dagger: group-relative continuations with decoupled clipping and dynamic sampling."""

from cpalgo.methods import register
from cpsim._lazy import lazy_exports

_LAZY = {"DAPO": "cpalgo.dapo.dapo", "dynamic_sampling_keep": "cpalgo.dapo.dapo",
         "decoupled_clip_objective": "cpalgo.dapo.dapo"}
__getattr__, __dir__ = lazy_exports("cpalgo.dapo", _LAZY, globals())
__all__ = list(_LAZY)

register("dapo", "DAPO: groups of 6 continuations from interaction states, decoupled clip, dynamic sampling",
         "cpalgo.dapo.dapo:DAPO", group="baseline", label="DAPO\u2020",
         components={"B": "-", "C": "-", "S": "-", "D": "-"}, replace=True)
