"""``python -m slam.run DATASET [SEQUENCE] ...``: the run command (see :mod:`slam.app.cli`)."""

from slam.app.cli import main
from slam.app.rerun_flush import exit_process

if __name__ == "__main__":
    exit_process(main())
