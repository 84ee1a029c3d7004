"""``python -m bench.report``: see ``bench.report.main``."""

import sys

from bench.report.main import main

sys.exit(main())
