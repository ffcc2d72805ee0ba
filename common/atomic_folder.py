"""An output folder that appears whole or not at all, written by one process at a time.

:func:`atomic_folder` first claims the target: a claim file beside it (``.NAME.claim``, created
with ``O_EXCL`` and holding the writer's pid), so a second writer is refused at once instead of
both writing and the last one silently winning. The content is written into a hidden sibling
(``.NAME.partial-PID``) that is renamed to the target at the end; on any error, Ctrl-C or
SIGTERM the sibling is removed and the target never appears. Creating both up front also proves
the folder is writable before any work is done. A claim or sibling left by a writer that was
killed (its pid no longer runs) is taken over.

This module is a leaf: it imports only the standard library.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

from common.atomic_io import fsync_folder


class FolderBusyError(ValueError):
    """The target is not new or empty, or another process is writing it (one-line message)."""


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _holder(claim: Path) -> int | None:
    """Pid written in a claim file (None when unreadable: being written, or foreign)."""
    try:
        return int(claim.read_text().strip() or "x")
    except (OSError, ValueError):
        return None


def _claim(claim: Path, target: Path) -> None:
    for _ in range(2):
        try:
            fd = os.open(claim, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            holder = _holder(claim)
            if holder is None or _running(holder):
                raise FolderBusyError(
                    f"{target}: another process (pid {holder}) is writing it; wait for it to "
                    f"finish, or remove {claim} if that process is gone"
                ) from None
            claim.unlink(missing_ok=True)  # its writer was killed: take the claim over
            continue
        with os.fdopen(fd, "w") as f:
            f.write(f"{os.getpid()}\n")
        return
    raise FolderBusyError(f"{target}: could not claim it ({claim} keeps reappearing)")


def _remove_stale_partials(parent: Path, name: str) -> None:
    for partial in parent.glob(f".{name}.partial-*"):
        pid = partial.name.rsplit("-", 1)[-1]
        if pid.isdigit() and not _running(int(pid)):
            shutil.rmtree(partial, ignore_errors=True)


def _check_new_or_empty(target: Path) -> None:
    if target.exists() and (not target.is_dir() or any(target.iterdir())):
        raise FolderBusyError(f"{target}: --out must be a new or empty folder")


@contextlib.contextmanager
def atomic_folder(target: str | Path) -> Iterator[Path]:
    """Claim ``target`` (a new or empty folder) and yield the hidden folder to write into;
    when the block ends normally it becomes ``target`` (see the module docstring)."""
    target = Path(target).absolute()
    _check_new_or_empty(target)
    parent = target.parent
    parent.mkdir(parents=True, exist_ok=True)
    claim = parent / f".{target.name}.claim"
    _claim(claim, target)
    try:
        _remove_stale_partials(parent, target.name)
        partial = parent / f".{target.name}.partial-{os.getpid()}"
        partial.mkdir()
        try:
            yield partial
            fsync_folder(partial)
            try:
                os.rename(partial, target)  # replaces an empty folder in one step
            except OSError as exc:
                if exc.errno in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR):
                    raise FolderBusyError(
                        f"{target}: was filled by another program meanwhile; nothing written"
                    ) from None
                raise
            fsync_folder(parent)
        except BaseException:
            shutil.rmtree(partial, ignore_errors=True)
            raise
    finally:
        claim.unlink(missing_ok=True)
