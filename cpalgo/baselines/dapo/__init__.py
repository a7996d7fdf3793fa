"""DAPO-dagger: group-relative continuations with decoupled clipping and dynamic sampling."""

import cpalgo.baselines.registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"DAPO": "cpalgo.baselines.dapo.dapo", "dynamic_sampling_keep": "cpalgo.baselines.dapo.dapo",
         "decoupled_clip_objective": "cpalgo.baselines.dapo.dapo"}
__getattr__, __dir__ = lazy_exports("cpalgo.baselines.dapo", _LAZY, globals())
__all__ = list(_LAZY)
