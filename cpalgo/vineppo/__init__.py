"""VinePPO-dagger: Monte Carlo root values from groups of continuations in PPO's advantages."""

import cpalgo.common.baseline_registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"VinePPO": "cpalgo.vineppo.vineppo"}
__getattr__, __dir__ = lazy_exports("cpalgo.vineppo", _LAZY, globals())
__all__ = list(_LAZY)
