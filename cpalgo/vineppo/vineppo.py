"""Moved to :mod:`cpalgo.baselines.vineppo.vineppo`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.vineppo.vineppo

sys.modules[__name__] = cpalgo.baselines.vineppo.vineppo
