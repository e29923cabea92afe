"""``python -m warpavatar.prepare``: the same as the ``warpavatar-prepare`` command."""

import sys

from warpavatar.cli.prepare import main

sys.exit(main())
