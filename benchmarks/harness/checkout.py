"""An earlier revision checked out beside the current tree, for before/after tables."""

from __future__ import annotations

import contextlib
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

from benchmarks.harness.paths import REPO


@contextlib.contextmanager
def checkout(revision: str) -> Iterator[Path]:
    """A detached git worktree of ``revision`` in a temporary folder, removed afterwards."""
    with tempfile.TemporaryDirectory(prefix="bench-before-") as tmp:
        path = Path(tmp) / "checkout"
        done = subprocess.run(
            ["git", "worktree", "add", "--detach", str(path), revision],
            cwd=REPO,
            capture_output=True,
            text=True,
        )
        if done.returncode != 0:
            message = (done.stderr.strip().splitlines() or ["?"])[-1]
            raise RuntimeError(f"cannot check out '{revision}': {message}")
        try:
            yield path
        finally:
            subprocess.run(
                ["git", "worktree", "remove", "--force", str(path)], cwd=REPO, capture_output=True
            )
