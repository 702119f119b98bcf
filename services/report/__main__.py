"""``python -m services.report``: :func:`services.report.cli.main`."""

import sys

from .cli import main

sys.exit(main())
