"""``python -m cpalgo.cli``: the ``counterplay`` command."""

from cpalgo.cli.parser import main

raise SystemExit(main())
