"""An exception as the one line a command prints after ``error:``."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path


def error_line(
    exc: BaseException, os_hints: Mapping[int, str], location: Path | None = None
) -> str:
    """``exc`` on one line, naming the file an ``OSError`` is about (or ``location``); an
    ``OSError`` whose errno is in ``os_hints`` (a full disk, a read-only file system) ends with
    that errno's fix."""
    if isinstance(exc, OSError) and exc.strerror and exc.errno in os_hints:
        where = exc.filename or location
        prefix = f"{where}: " if where else ""
        return f"{prefix}{exc.strerror}; {os_hints[exc.errno]}"
    text = " ".join(str(exc).split())
    if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in text:
        text = f"{exc.filename}: {text}"
    return text or type(exc).__name__
