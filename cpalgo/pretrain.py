"""Moved to :mod:`cpalgo.anchor.imitation`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.anchor.imitation

sys.modules[__name__] = cpalgo.anchor.imitation
