"""Moved to :mod:`cpalgo.baselines.craft.craft`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.craft.craft

sys.modules[__name__] = cpalgo.baselines.craft.craft
