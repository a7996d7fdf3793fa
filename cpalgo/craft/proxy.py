"""Moved to :mod:`cpalgo.baselines.craft.proxy`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.craft.proxy

sys.modules[__name__] = cpalgo.baselines.craft.proxy
