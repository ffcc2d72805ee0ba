"""SIGTERM handled as Ctrl-C is: Docker, systemd and Slurm stop a job with it, and a run must
then leave only complete files (and a run status that says it was terminated)."""

from __future__ import annotations

import contextlib
import os
import signal

_MAIN_PID: int | None = None
_AT_FORK_REGISTERED = False


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when SIGTERM arrives (a :class:`KeyboardInterrupt`, so every
    cleanup that handles Ctrl-C handles it too)."""


def _raise_terminated(signum: int, frame: object) -> None:
    if os.getpid() != _MAIN_PID:  # a forked worker (multiprocessing) inherited the handler
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTERM)
        return
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # one is enough: let the cleanup finish
    raise Terminated()


def handle_sigterm():
    """Turn SIGTERM into :class:`Terminated` in this process (main thread only; elsewhere a
    no-op); returns the previous handler for :func:`restore_sigterm`. Forked children get
    SIGTERM's default back at once (a pool's ``terminate()`` must end even a stuck worker)."""
    global _MAIN_PID, _AT_FORK_REGISTERED
    _MAIN_PID = os.getpid()
    if not _AT_FORK_REGISTERED:  # a forked worker may deadlock before running Python code:
        os.register_at_fork(after_in_child=_default_in_child)  # only SIG_DFL ends it then
        _AT_FORK_REGISTERED = True
    with contextlib.suppress(ValueError):
        return signal.signal(signal.SIGTERM, _raise_terminated)
    return None


def restore_sigterm(previous) -> None:
    """Put back the handler :func:`handle_sigterm` replaced (``previous``: what it returned)."""
    if previous is None:
        return
    with contextlib.suppress(ValueError):
        signal.signal(signal.SIGTERM, previous)


def _default_in_child() -> None:
    if signal.getsignal(signal.SIGTERM) is _raise_terminated:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
