"""``python -m cpalgo.traffic``: see :mod:`cpalgo.traffic.cli`."""

import sys

from cpalgo.traffic.cli import main

sys.exit(main())
