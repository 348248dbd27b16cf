"""``python -m esmicp``: the ``esmicp`` command."""

import sys

from .cli import main

sys.exit(main())
