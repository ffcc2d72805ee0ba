"""``python -m slam.merge RUN_DIR RUN_DIR ... --out DIR`` (see :mod:`slam.app.merge_cli`)."""

from slam.app.merge_cli import main
from slam.app.rerun_flush import exit_process

if __name__ == "__main__":
    exit_process(main())
