"""``python -m thermbench.cli ...``: the ``thermbench`` command."""

import sys

from .entry import main

sys.exit(main())
