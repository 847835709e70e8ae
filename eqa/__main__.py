"""``python -m eqa`` = the ``eqa`` command."""

from eqa.app.cli import main

raise SystemExit(main())
