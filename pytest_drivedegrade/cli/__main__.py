"""`python -m pytest_drivedegrade.cli`: the `drivedegrade` command, where the console script is not on PATH."""

from . import main

raise SystemExit(main())
