"""VinePPO-dagger: Monte Carlo root values from groups of continuations in PPO's advantages."""

from cpalgo.methods import register
from cpsim._lazy import lazy_exports

_LAZY = {"VinePPO": "cpalgo.vineppo.vineppo"}
__getattr__, __dir__ = lazy_exports("cpalgo.vineppo", _LAZY, globals())
__all__ = list(_LAZY)

register("vineppo", "VinePPO: critic value at interaction states replaced by the mean return of 6 continuations",
         "cpalgo.vineppo.vineppo:VinePPO", group="baseline", label="VinePPO\u2020",
         components={"B": "-", "C": "-", "S": "-", "D": "-"}, replace=True)
