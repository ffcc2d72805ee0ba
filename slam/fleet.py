"""``python -m slam.fleet MANIFEST --out DIR``: many runs on Ray, merged (see
:mod:`slam.app.fleet_cli`)."""

import sys

from slam.app.fleet_cli import main

if __name__ == "__main__":
    sys.exit(main())
