"""``python -m warpnerf.cli``: the same command line as the ``warpnerf`` console script."""

import sys

from warpnerf.cli import main

sys.exit(main())
