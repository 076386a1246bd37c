"""``python -m polrig.models.continuum``."""

import sys


from polrig.models.continuum.cli import main

sys.exit(main())
