"""``python -m gcrsky ...`` is the ``gcrsky`` command."""

from .cli import main

raise SystemExit(main())
