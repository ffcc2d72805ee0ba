"""``python -m slam.run DATASET [SEQUENCE] ...``: the run command (see :mod:`slam.app.cli`)."""

import sys

from slam.app.cli import main

if __name__ == "__main__":
    sys.exit(main())
