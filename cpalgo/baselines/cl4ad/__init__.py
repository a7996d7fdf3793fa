"""CL4AD-dagger: self-play worlds reset into scenarios of high learnability."""

import cpalgo.baselines.registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"CL4AD": "cpalgo.baselines.cl4ad.cl4ad", "LearnabilitySampler": "cpalgo.baselines.cl4ad.curriculum",
         "CurriculumReset": "cpalgo.baselines.cl4ad.curriculum"}
__getattr__, __dir__ = lazy_exports("cpalgo.baselines.cl4ad", _LAZY, globals())
__all__ = list(_LAZY)
