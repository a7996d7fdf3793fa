"""Moved to :mod:`cpalgo.baselines.spiced.reference`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.spiced.reference

sys.modules[__name__] = cpalgo.baselines.spiced.reference
