"""Moved to :mod:`cpalgo.baselines.plannerrft.policies`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.plannerrft.policies

sys.modules[__name__] = cpalgo.baselines.plannerrft.policies
