"""DAPO-dagger: group-relative continuations with decoupled clipping and dynamic sampling."""

import cpalgo.common.baseline_registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"DAPO": "cpalgo.dapo.dapo", "dynamic_sampling_keep": "cpalgo.dapo.dapo",
         "decoupled_clip_objective": "cpalgo.dapo.dapo"}
__getattr__, __dir__ = lazy_exports("cpalgo.dapo", _LAZY, globals())
__all__ = list(_LAZY)
