"""Rerun's web viewer page, served on a chosen address.

rerun-sdk 0.41's ``rr.serve_web_viewer`` takes no bind address and listens on every interface
(``0.0.0.0``), although the gRPC data server beside it is bound to ``viz.serve_bind_ip``. The
``rerun`` command shipped with the SDK does take one (``--bind``), and with a gRPC URL argument it
serves only the page, which connects to that URL. :class:`WebViewerServer` runs it as a child
process for the life of the run, so the page listens only on the configured address.
"""

from __future__ import annotations

import contextlib
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


class WebViewerServer:
    """The web viewer page on ``http://bind_ip:web_port``, connecting to ``grpc_uri``."""

    def __init__(self, bind_ip: str, web_port: int, grpc_uri: str, timeout_s: float = 20.0):
        executable = _rerun_binary()
        if executable is None:
            raise RuntimeError("the 'rerun' command of rerun-sdk is not installed; reinstall it")
        if _listening(bind_ip, web_port):
            raise OSError(
                f"viz.serve_web_port {web_port}: already in use on {bind_ip}; pass "
                "--set viz.serve_web_port=PORT"
            )
        self.url = f"http://{bind_ip}:{web_port}/?url={quote(grpc_uri, safe='')}"
        self._process = subprocess.Popen(
            [
                executable,
                "--serve-web",
                "--bind",
                bind_ip,
                "--web-viewer-port",
                str(web_port),
                grpc_uri,
            ],
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
