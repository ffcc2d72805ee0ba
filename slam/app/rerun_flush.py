"""Closing a Rerun recording without hanging: Rerun's ``flush`` waits for ever by default, and a
sink that cannot take the data (a full disk, a viewer gone) never confirms it.

Dropping such a stream, disconnecting it, or Rerun's own clean-up at the interpreter's exit wait
on the same sink. So a stream whose flush gave up is kept here, never dropped, and a command
ends through :func:`exit_process`, which then leaves without that clean-up. A process that ends
otherwise (a Ray worker, whose exit Ray starts after the task returned) calls
:func:`leave_at_exit_if_given_up`.
"""

from __future__ import annotations

import atexit
import logging
import os
import sys
from typing import NoReturn

log = logging.getLogger(__name__)

_GIVEN_UP: list = []
"""Streams whose sink did not take their data in time (see the module docstring)."""

FLUSH_TIMEOUT_S = 10.0
"""Default wait for a recording to be written or sent when it is closed."""


def flush_recording(rec, timeout_s: float, what: str) -> bool:
    """Wait up to ``timeout_s`` for Rerun to write or send what ``rec`` holds; a sink that
    cannot take it (a full disk, a viewer gone) would otherwise block for ever. Returns whether
    it all went out; if not, warns that ``what`` may miss its end (the caller must then not
    disconnect the stream: that waits on the same sink)."""
    try:
        rec.flush(timeout_sec=timeout_s)
    except RuntimeError as exc:  # a timeout, or a sink that gave up (Rerun says which)
        reason = " ".join(str(exc).split())
        log.warning("%s could not be written completely (%s); it may miss its end", what, reason)
        _GIVEN_UP.append(rec)
        return False
    return True


def exit_process(status: int) -> NoReturn:
    """End a command with ``status``. Where a recording was given up, the process leaves at
    once (``os._exit``, after flushing the logs and the standard streams): every other output is
    already on disk, and the interpreter's clean-up would wait for ever on that stream's sink."""
    if not _GIVEN_UP:
        sys.exit(status)
    _leave(status)


def leave_at_exit_if_given_up() -> None:
    """Where a recording was given up, the interpreter's exit (with status 0) leaves at once
    instead of waiting for ever in Rerun's clean-up: exit hooks run last registered first, so
    this one runs before Rerun's. For a process that cannot end through :func:`exit_process`."""
    if _GIVEN_UP:
        atexit.unregister(_leave)
        atexit.register(_leave, 0)


def _leave(status: int) -> NoReturn:
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
