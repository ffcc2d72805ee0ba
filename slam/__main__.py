"""``python -m slam ...`` is ``python -m slam.run ...``."""

from slam.app.cli import main
from slam.app.rerun_flush import exit_process

exit_process(main())
