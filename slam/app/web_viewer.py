"""Rerun's web viewer page, served on a chosen address.

rerun-sdk 0.41's ``rr.serve_web_viewer`` takes no bind address and listens on every interface
(``0.0.0.0``), although the gRPC data server beside it is bound to ``viz.serve_bind_ip``. The
``rerun`` command shipped with the SDK does take one (``--bind``), and with a gRPC URL argument it
serves only the page, which connects to that URL. :class:`WebViewerServer` runs it as a child
process for the life of the run, so the page listens only on the configured address. On Linux the
child gets SIGTERM when the run's process dies, even by SIGKILL or the OOM killer
(``PR_SET_PDEATHSIG``), so no orphaned server keeps the port. A short Python program sets that and
then becomes the server (``exec``): Python code run between ``fork`` and ``exec`` (``preexec_fn``)
can deadlock in a process with other threads, and the run's has Rerun's, torch's and the workers'.

:func:`check_bindable` probes both ports before either server starts: a taken port or an address
that is not this machine's is one line naming the setting to change.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import quote


def viewer_executable() -> str | None:
    """The ``rerun`` command next to this interpreter (a venv not on PATH), else PATH's."""
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.is_file() else shutil.which("rerun")


def _rerun_binary() -> str | None:
    """The ``rerun`` binary itself: the command on PATH is a Python wrapper that runs it as a
    child, so stopping the wrapper alone would leave the server running."""
    try:
        import rerun_cli
    except ImportError:
        return viewer_executable()
    binary = Path(rerun_cli.__file__).parent / "rerun"
    return str(binary) if binary.is_file() else viewer_executable()


def _listening(host: str, port: int) -> bool:
    probe = "127.0.0.1" if host in ("0.0.0.0", "") else ("::1" if host == "::" else host)
    family = socket.AF_INET6 if ":" in probe else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.settimeout(0.2)
        return sock.connect_ex((probe, port)) == 0


def check_bindable(bind_ip: str, port: int, setting: str) -> None:
    """Raise a one-line ``OSError`` naming ``setting`` when ``bind_ip:port`` cannot be listened
    on: the port is taken, or the address is not one of this machine's."""
    family = socket.AF_INET6 if ":" in bind_ip else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers do: TIME_WAIT
        try:
            sock.bind((bind_ip, port))
        except socket.gaierror:
            raise OSError(
                f"viz.serve_bind_ip {bind_ip}: not an IP address; pass one of this machine's, "
                "e.g. 127.0.0.1"
            ) from None
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise OSError(
                    f"{setting} {port}: already in use on {bind_ip} (another viewer or run?); "
                    f"pass --set {setting}=PORT"
                ) from None
            if exc.errno == errno.EADDRNOTAVAIL:
                raise OSError(
                    f"viz.serve_bind_ip {bind_ip}: not an address of this machine; pass one of "
                    "its own, e.g. 127.0.0.1 (reach it through an SSH port forward)"
                ) from None
            raise OSError(
                f"{setting} {port}: cannot listen on {bind_ip} ({exc.strerror or exc}); pass "
                f"--set {setting}=PORT"
            ) from None


def check_serve_ports(bind_ip: str, grpc_port: int, web_port: int) -> None:
    """:func:`check_bindable` for both servers of ``viz.mode: serve``."""
    check_bindable(bind_ip, grpc_port, "viz.serve_grpc_port")
    check_bindable(bind_ip, web_port, "viz.serve_web_port")


_DIE_WITH_PARENT = """
import ctypes, os, signal, sys
ctypes.CDLL(None).prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
if os.getppid() != int(sys.argv[1]):  # the parent died before that
    os._exit(1)
os.execv(sys.argv[2], sys.argv[2:])
"""
"""Run as ``python -c _DIE_WITH_PARENT PARENT_PID COMMAND...``: COMMAND, in this process, gets
SIGTERM when PARENT_PID dies (the setting outlives ``exec``)."""


def _dying_with_this_process(command: list[str]) -> list[str]:
    """``command``, set to get SIGTERM when this process dies (Linux; elsewhere unchanged)."""
    if not sys.platform.startswith("linux"):
        return command
    return [sys.executable, "-I", "-S", "-c", _DIE_WITH_PARENT, str(os.getpid()), *command]


class WebViewerServer:
    """The web viewer page on ``http://bind_ip:web_port``, connecting to ``grpc_uri``."""

    def __init__(self, bind_ip: str, web_port: int, grpc_uri: str, timeout_s: float = 20.0):
        executable = _rerun_binary()
        if executable is None:
            raise RuntimeError("the 'rerun' command of rerun-sdk is not installed; reinstall it")
        check_bindable(bind_ip, web_port, "viz.serve_web_port")
        self.url = f"http://{bind_ip}:{web_port}/?url={quote(grpc_uri, safe='')}"
        command = [executable, "--serve-web", "--bind", bind_ip]
        command += ["--web-viewer-port", str(web_port), grpc_uri]
        self._process = subprocess.Popen(
            _dying_with_this_process(command),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,  # its own process group: close() stops all of it
        )
        deadline = time.monotonic() + timeout_s
        while not _listening(bind_ip, web_port):
            if self._process.poll() is not None or time.monotonic() > deadline:
                self.close()
                raise OSError(
                    f"the web viewer did not start on {bind_ip}:{web_port}; check that the "
                    "address is this machine's (viz.serve_bind_ip) and the port is free"
                )
            time.sleep(0.05)

    @property
    def pid(self) -> int:
        return self._process.pid

    def close(self) -> None:
        """Stop serving the page (idempotent)."""
        if self._process.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self._process.pid, signal.SIGTERM)
        try:
            self._process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self._process.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._process.wait(timeout=5)
