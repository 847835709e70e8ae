"""``python -m eqa`` = the ``eqa`` command."""

from eqa.cli import main

raise SystemExit(main())
