"""Moved to :mod:`cpalgo.baselines.dapo`; this package path stays importable."""

import cpalgo.baselines.dapo as _new


def __getattr__(name: str):
    return getattr(_new, name)


def __dir__() -> list[str]:
    return dir(_new)
