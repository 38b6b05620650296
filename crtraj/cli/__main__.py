"""``python -m crtraj.cli``: the ``crtraj`` command."""

import sys

from crtraj.cli import main

sys.exit(main())
