"""Moved to :mod:`cpalgo.baselines.dapo.dapo`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.dapo.dapo

sys.modules[__name__] = cpalgo.baselines.dapo.dapo
