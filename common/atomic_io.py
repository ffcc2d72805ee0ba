"""Atomic, durable file writes: a reader never sees a half-written file, even after a crash or a
power loss.

Every writer goes through :func:`atomic_path`: the content is written to a hidden temporary file
in the target's folder (``.NAME.XXXX.tmp.SUFFIX``), flushed to disk (``fsync``), given the mode
``open()`` would give (``0666`` minus the umask; ``mkstemp`` alone gives ``0600``), renamed over
the target and the folder is fsynced so that the rename itself survives a power loss. On any
error (and on ``KeyboardInterrupt``/``SystemExit``) the temporary file is removed.

This module is a leaf: it imports only the standard library, so ``frontends/``, ``mapping/`` and
``slam/`` may all use it.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

TMP_SUFFIX = ".tmp"
"""Marks every temporary file these helpers create: hidden, ``.NAME.<random>.tmp<suffix>``."""


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """Mode of a newly written file: what ``open()`` would give under the current umask."""
    return 0o666 & ~_umask()


def fsync_folder(folder: Path) -> None:
    """Flush a folder's entries (a rename or a new file) to disk; a no-op where unsupported."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):  # some file systems refuse fsync on a folder
            os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; when the block ends normally, make it ``path``.

    For writers that want a file name (``np.savez``, ``torch.save``, ``trimesh.export``). The
    temporary file exists (empty) when the block starts.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The target's suffix last: writers that infer the format from it (np.savez adds ".npz"
    # to other names, matplotlib and PIL pick the encoder) write to the temporary file itself.
    fd, name = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=f"{TMP_SUFFIX}{path.suffix}", dir=path.parent
    )
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        _fsync_file(tmp)
        os.chmod(tmp, file_mode())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_folder(path.parent)


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically and durably."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)


def write_text_atomic(path: str | Path, text: str, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` atomically and durably."""
    write_bytes_atomic(path, text.encode(encoding))


def write_problem(folder: Path) -> str | None:
    """Why no file can be created in ``folder`` (the OS's reason), or None when one can. Tried
    with a temporary file, not ``os.access``: root passes access checks on a read-only mount."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        return exc.strerror or str(exc)
    return None
