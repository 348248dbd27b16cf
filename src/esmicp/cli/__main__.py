"""``python -m esmicp.cli``: the ``esmicp`` command."""

import sys

from . import main

sys.exit(main())
