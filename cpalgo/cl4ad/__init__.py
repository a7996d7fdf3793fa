"""CL4AD-dagger: self-play worlds reset into scenarios of high learnability."""

import cpalgo.common.baseline_registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"CL4AD": "cpalgo.cl4ad.cl4ad", "LearnabilitySampler": "cpalgo.cl4ad.curriculum",
         "CurriculumReset": "cpalgo.cl4ad.curriculum"}
__getattr__, __dir__ = lazy_exports("cpalgo.cl4ad", _LAZY, globals())
__all__ = list(_LAZY)
