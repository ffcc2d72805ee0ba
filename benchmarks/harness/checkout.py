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


@contextlib.contextmanager
def revisions(before: str | None, label: str = "before {rev}") -> Iterator[dict[str, Path | None]]:
    """The code a before/after benchmark measures, by row label: a checkout of ``before``
    (labelled ``label``) where one is asked for, then this tree (``"after"``: None)."""
    if before is None:
        yield {"after": None}
        return
    with checkout(before) as path:
        yield {label.format(rev=before): path, "after": None}
