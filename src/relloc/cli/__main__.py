"""``python -m relloc.cli``: the ``relloc`` command."""

from relloc.cli import main

raise SystemExit(main())
