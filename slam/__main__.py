"""``python -m slam ...`` is ``python -m slam.run ...``."""

import sys

from slam.run import main

sys.exit(main())
