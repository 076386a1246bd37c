"""``python -m polrig``: the ``polrig`` console script."""

import sys

from polrig.cli import main

if __name__ == "__main__":
    sys.exit(main())
