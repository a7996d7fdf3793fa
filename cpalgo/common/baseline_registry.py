"""Moved to :mod:`cpalgo.baselines.registry`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.registry

sys.modules[__name__] = cpalgo.baselines.registry
