"""Moved to :mod:`cpalgo.baselines.cl4ad.curriculum`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.cl4ad.curriculum

sys.modules[__name__] = cpalgo.baselines.cl4ad.curriculum
