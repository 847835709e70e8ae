"""``python -m eqa_app`` = the ``eqa`` command."""

from eqa_app.cli import main

raise SystemExit(main())
