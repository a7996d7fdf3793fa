"""Moved to :mod:`cpalgo.baselines.cl4ad.cl4ad`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.cl4ad.cl4ad

sys.modules[__name__] = cpalgo.baselines.cl4ad.cl4ad
