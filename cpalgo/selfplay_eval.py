"""Moved to :mod:`cpalgo.anchor.outcomes`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.anchor.outcomes

sys.modules[__name__] = cpalgo.anchor.outcomes
