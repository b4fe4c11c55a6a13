"""``python -m isac_twin.cli`` = ``isac-twin``."""

import sys

from .main import main

sys.exit(main())
