"""``python -m isac_twin.cli`` = ``isac-twin``."""

import sys

from . import main

sys.exit(main())
