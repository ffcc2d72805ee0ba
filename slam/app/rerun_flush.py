"""Closing a Rerun recording without hanging: Rerun's ``flush`` waits for ever by default, and a
sink that cannot take the data (a full disk, a viewer gone) never confirms it."""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

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
        return False
    return True
