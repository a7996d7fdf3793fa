"""Moved to :mod:`cpalgo.anchor.teacher_ppo`; this module path stays importable (it is the same module)."""

import sys

import cpalgo.anchor.teacher_ppo

sys.modules[__name__] = cpalgo.anchor.teacher_ppo
