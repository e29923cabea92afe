"""``python -m warpavatar.prepare``: the same as the ``warpavatar-prepare`` command."""

import sys

from warpavatar.prepare.cli import main

sys.exit(main())
