"""Where benchmarks read data and write results, and the one way they write a section."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data"
RESULTS_DIR = REPO / "benchmarks" / "results"
WORK_DIR = REPO / "benchmarks" / "out"


def write_text(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (readers never see half a file), world-readable."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    with os.fdopen(fd, "w") as stream:
        stream.write(text)
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)
    return path
