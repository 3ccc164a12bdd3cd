"""``python -m thermbench.cli ...``: the ``thermbench`` command."""

import sys

from .main import main

sys.exit(main())
