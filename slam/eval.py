"""``python -m slam.eval RUN_DIR`` and ``python -m slam.eval transform``: the evaluation command
(see :mod:`slam.evaluation.cli`)."""

import sys

from slam.evaluation.cli import main

if __name__ == "__main__":
    sys.exit(main())
