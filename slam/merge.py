"""``python -m slam.merge RUN_DIR RUN_DIR ... --out DIR`` (see :mod:`slam.app.merge_cli`)."""

import sys

from slam.app.merge_cli import main

if __name__ == "__main__":
    sys.exit(main())
