"""Moved to :mod:`cpalgo.anchor.compress`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.anchor.compress

sys.modules[__name__] = cpalgo.anchor.compress
