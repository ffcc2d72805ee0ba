"""Regenerate the README pictures in docs/figures/ (about 5 minutes on 2 cores).

    python docs/make_figures.py

Runs the demo (generated RGB-D room) and the generated LiDAR street loop (KITTI layout) with
``python -m slam.run`` into a temporary folder, then ``python -m slam.eval RUN --figures DIR``
renders each run's top-down trajectories with loop edges, a shaded mesh snapshot and the mesh
coloured by its distance to ground truth, offscreen (matplotlib Agg: no display, no GPU).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
FIGURES = REPO_ROOT / "docs" / "figures"
RUNS = {
    "demo": ["demo"],
    "generated-lidar": ["generated-lidar"],
}


def run(*args: str) -> None:
    print("+", " ".join(args), flush=True)
    subprocess.run([sys.executable, *args], cwd=REPO_ROOT, check=True)


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="figures-") as tmp:
        for name, dataset in RUNS.items():
            out = Path(tmp) / name
            run("-m", "slam.run", *dataset, "--no-viz", "--no-progress", "--out", str(out))
            run("-m", "slam.eval", str(out), "--no-plots", "--figures", str(FIGURES / name))
    return 0


if __name__ == "__main__":
    sys.exit(main())
