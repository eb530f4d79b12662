"""``python -m vpengine``: the same as the ``vpengine`` console script."""

import sys

from vpengine.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
