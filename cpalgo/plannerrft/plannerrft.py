"""Moved to :mod:`cpalgo.baselines.plannerrft.plannerrft`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.plannerrft.plannerrft

sys.modules[__name__] = cpalgo.baselines.plannerrft.plannerrft
