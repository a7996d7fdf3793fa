"""Moved to :mod:`cpalgo.baselines.continuations`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.continuations

sys.modules[__name__] = cpalgo.baselines.continuations
