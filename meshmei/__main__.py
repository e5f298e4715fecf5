"""``python -m meshmei``: the same command line as ``meshmei`` (:func:`meshmei.cli.main`)."""

import sys

from .cli import main

sys.exit(main())
