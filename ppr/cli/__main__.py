"""``python -m ppr.cli``: the ``ppr`` command."""

import sys

from . import main

sys.exit(main())
