"""CL4AD-dagger: self-play worlds reset into scenarios of high learnability."""

from cpalgo.methods import register
from cpsim._lazy import lazy_exports

_LAZY = {"CL4AD": "cpalgo.cl4ad.cl4ad", "LearnabilitySampler": "cpalgo.cl4ad.curriculum",
         "CurriculumReset": "cpalgo.cl4ad.curriculum"}
__getattr__, __dir__ = lazy_exports("cpalgo.cl4ad", _LAZY, globals())
__all__ = list(_LAZY)

register("cl4ad", "CL4AD: learnability curriculum (scenarios with success near 0.5) instead of uniform sampling",
         "cpalgo.cl4ad.cl4ad:CL4AD", group="baseline", label="CL4AD\u2020",
         components={"B": "-", "C": "-", "S": "-", "D": "-"}, replace=True)
