"""``python -m slam ...`` is ``python -m slam.run ...``."""

import sys

from slam.app.cli import main

sys.exit(main())
