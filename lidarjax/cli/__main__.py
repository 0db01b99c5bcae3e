"""``python -m lidarjax.cli``: the ``lidarjax`` command line."""

import sys

from ._main import main

sys.exit(main())
