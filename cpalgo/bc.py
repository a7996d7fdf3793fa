"""Moved to :mod:`cpalgo.traffic`: the model, its data and training in
:mod:`cpalgo.traffic.bc`, :func:`~cpalgo.traffic.measure.measure_traffic`, the command in
:mod:`cpalgo.traffic.cli`. This module path stays importable (the same objects) and
``python -m cpalgo.bc`` still runs the command."""

import sys

from cpalgo.traffic.bc import *  # noqa: F401,F403
from cpalgo.traffic.cli import main
from cpalgo.traffic.measure import measure_traffic  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
