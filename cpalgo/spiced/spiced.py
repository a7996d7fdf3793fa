"""Moved to :mod:`cpalgo.baselines.spiced.spiced`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.baselines.spiced.spiced

sys.modules[__name__] = cpalgo.baselines.spiced.spiced
