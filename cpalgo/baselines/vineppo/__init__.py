"""VinePPO-dagger: Monte Carlo root values from groups of continuations in PPO's advantages."""

import cpalgo.baselines.registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"VinePPO": "cpalgo.baselines.vineppo.vineppo"}
__getattr__, __dir__ = lazy_exports("cpalgo.baselines.vineppo", _LAZY, globals())
__all__ = list(_LAZY)
