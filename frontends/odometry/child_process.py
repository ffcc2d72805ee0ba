"""An odometry that runs in a child process, so that its native code leaves this process's threads
alone.

KISS-ICP's Python bindings hold the GIL for a whole registration (about 30 ms of a 128k-point
scan), so while the main thread registers, the pipeline's submap and map worker threads cannot run
a line of Python: they fall behind and the main thread then waits for them. Behind a process
boundary the main thread waits on a socket, with the GIL released, and the workers run meanwhile.

Each call crosses as a pickle (protocol 5) whose arrays travel out of band through a shared
memory file (``memfd``) per direction, so a scan is copied twice (into the file and out of it)
instead of being pickled and pushed through the socket (measured on 128k-point scans: 5.5 ms a
round trip of 3 MB each way through the socket; through the files a whole call took 2-4 ms more
than registering in this process). Errors raised by the odometry
(e.g. :class:`~frontends.errors.DatasetError` for an empty scan) are raised again here.

Every reply must come within ``reply_timeout_s`` (``odometry.child_reply_timeout_s`` of a run):
a child that hangs is killed and one that died is reported, each as an
:class:`~frontends.errors.OdometryProcessError` whose one line says what happened and what to do,
never a hang. The child dies with its parent (``PR_SET_PDEATHSIG``), ignores Ctrl-C and SIGTERM
(the parent handles them and closes the socket), and leaves quietly when the parent is gone.

Linux only (``os.memfd_create``); :func:`child_process_available` says whether it can be used.
"""

from __future__ import annotations

import contextlib
import ctypes
import mmap
import os
import pickle
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from frontends.errors import OdometryProcessError
from frontends.frame import Frame
from frontends.odometry.base import Odometry, OdometryResult

INITIAL_BYTES = 8 << 20
"""First size of each shared file (a 128k-point float64 scan is 3 MB); it grows on demand."""

DEFAULT_REPLY_TIMEOUT_S = 120.0
"""How long a reply of the child may take by default: a registration takes 30-100 ms and
building the odometry (importing KISS-ICP) a few seconds, so two minutes means it hangs."""

POLL_S = 0.5
"""While waiting for a reply, how often the child is checked for having exited."""

_PR_SET_PDEATHSIG = 1


def child_process_available() -> bool:
    """Whether this platform can run an odometry in a child process (needs ``memfd_create``)."""
    return hasattr(os, "memfd_create") and sys.platform.startswith("linux")


class _SharedFile:
    """One direction's shared memory file: the writer grows it, the reader maps what it is told."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self._map: mmap.mmap | None = None

    def _mapped(self, size: int) -> mmap.mmap:
        if self._map is None or len(self._map) < size:
            if self._map is not None:
                self._map.close()
            self._map = mmap.mmap(self.fd, max(size, os.fstat(self.fd).st_size))
        return self._map

    def write(self, buffers: list[memoryview]) -> list[tuple[int, int]]:
        """Copy ``buffers`` into the file back to back; their ``(offset, size)`` spans."""
        spans, offset = [], 0
        for buffer in buffers:
            spans.append((offset, buffer.nbytes))
            offset += buffer.nbytes
        size = os.fstat(self.fd).st_size
        if offset > size:
            os.ftruncate(self.fd, max(offset, 2 * size))
        with memoryview(self._mapped(offset)) as view:
            for (start, size), buffer in zip(spans, buffers, strict=True):
                view[start : start + size] = buffer.cast("B")
        return spans

    def read(self, spans: list[tuple[int, int]]) -> list[bytearray]:
        """Copies of the spans (the next message overwrites the file)."""
        if not spans:
            return []
        with memoryview(self._mapped(max(start + size for start, size in spans))) as view:
            return [bytearray(view[start : start + size]) for start, size in spans]

    def close(self) -> None:
        if self._map is not None:
            self._map.close()
            self._map = None
        os.close(self.fd)


class _Channel:
    """Pickled messages over a socket, their arrays through the two shared files."""

    def __init__(self, conn: Connection, outgoing: _SharedFile, incoming: _SharedFile) -> None:
        self.conn = conn
        self.outgoing = outgoing
        self.incoming = incoming

    def send(self, message: Any) -> None:
        buffers: list[pickle.PickleBuffer] = []
        header = pickle.dumps(message, protocol=5, buffer_callback=buffers.append)
        spans = self.outgoing.write([buffer.raw() for buffer in buffers])
        self.conn.send_bytes(pickle.dumps((header, spans), protocol=5))

    def receive(self, ready: Any = None) -> Any:
        """The next message; ``ready()`` is called first and must return once one is there."""
        if ready is not None:
            ready()
        header, spans = pickle.loads(self.conn.recv_bytes())
        return pickle.loads(header, buffers=self.incoming.read(spans))

    def close(self) -> None:
        self.conn.close()
        self.outgoing.close()
        self.incoming.close()


@dataclass(frozen=True)
class ProcessUsage:
    """Resources of the child process so far (from ``/proc``)."""

    cpu_s: float
    rss_mb: float
    peak_rss_mb: float


class ChildProcessOdometry(Odometry):
    """The odometry ``make_odometry(name, **options)`` built and run in a child process.

    Results equal the same odometry's in this process (same code, same inputs, same thread
    count). The child exits when :meth:`close` is called, when this object is collected, or when
    this process ends (it reads end-of-file then, or is killed with it).

    Args:
        name, options: the odometry, as for ``make_odometry``.
        reply_timeout_s: the longest a call may wait for the child's reply; a child that takes
            longer is killed and the call raises :class:`OdometryProcessError`.
    """

    def __init__(
        self, name: str, reply_timeout_s: float = DEFAULT_REPLY_TIMEOUT_S, **options: Any
    ) -> None:
        if reply_timeout_s <= 0:
            raise ValueError(f"reply_timeout_s must be positive, got {reply_timeout_s}")
        self.reply_timeout_s = reply_timeout_s
        if not child_process_available():
            raise RuntimeError("ChildProcessOdometry needs Linux (os.memfd_create)")
        parent_socket, child_socket = socket.socketpair()
        to_child = os.memfd_create("odometry-frames")
        to_parent = os.memfd_create("odometry-results")
        for fd in (to_child, to_parent):
            os.ftruncate(fd, INITIAL_BYTES)
        root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [root, env.get("PYTHONPATH")]))
        fds = (child_socket.fileno(), to_child, to_parent)
        self._process = subprocess.Popen(
            [sys.executable, "-m", __name__, *map(str, fds), str(os.getpid())],
            pass_fds=fds,
            env=env,
        )
        child_socket.close()
        self._channel = _Channel(
            Connection(parent_socket.detach()), _SharedFile(to_child), _SharedFile(to_parent)
        )
        self.name = name
        self._call("build", (name, options))

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self._process.pid

    @property
    def exit_code(self) -> int | None:
        """The child's exit status, None while it runs."""
        return self._process.poll()

    def _call(self, method: str, argument: Any = None) -> Any:
        if self._channel is None:
            raise RuntimeError("the odometry process was closed")
        try:
            self._channel.send((method, argument))
            status, value = self._channel.receive(lambda: self._wait_for_reply(method))
        except (EOFError, OSError) as exc:
            code = self._process.poll()
            raise OdometryProcessError(
                f"the {self.name} odometry process ended (exit code {code}) during '{method}'; "
                "its own error, if any, is printed above; rerun, or set "
                "odometry.child_process=false to run it in this process"
            ) from exc
        if status == "error":
            raise value
        return value

    def _wait_for_reply(self, method: str) -> None:
        """Return once a reply (or end-of-file) is there; kill the child and raise when none
        came within :attr:`reply_timeout_s`."""
        assert self._channel is not None
        deadline = time.monotonic() + self.reply_timeout_s
        while not self._channel.conn.poll(max(0.0, min(POLL_S, deadline - time.monotonic()))):
            if self._process.poll() is not None:
                return  # it exited: the socket reads end-of-file, reported by the caller
            if time.monotonic() >= deadline:
                self._process.kill()
                self._process.wait()
                self._channel.close()
                self._channel = None
                raise OdometryProcessError(
                    f"the {self.name} odometry process gave no reply to '{method}' within "
                    f"{self.reply_timeout_s:g} s and was stopped; if the machine is just slow, "
                    "raise odometry.child_reply_timeout_s, else set "
                    "odometry.child_process=false to run it in this process"
                )

    def register(self, frame: Frame) -> OdometryResult:
        result, self.num_failures = self._call("register", frame)
        return result

    def restart_covariance(self) -> None:
        self._call("restart_covariance")

    def child_cpu_s(self) -> float:
        return self.usage().cpu_s

    def usage(self) -> ProcessUsage:
        """CPU time and memory of the child so far."""
        with open(f"/proc/{self.pid}/stat") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()
        ticks = os.sysconf("SC_CLK_TCK")
        cpu_s = (int(fields[11]) + int(fields[12])) / ticks  # utime, stime
        memory = {}
        with open(f"/proc/{self.pid}/status") as status:
            for line in status:
                key, _, value = line.partition(":")
                if key in ("VmRSS", "VmHWM"):
                    memory[key] = int(value.split()[0]) / 1024
        return ProcessUsage(cpu_s, memory["VmRSS"], memory["VmHWM"])

    def close(self) -> None:
        """End the child process (idempotent)."""
        if self._channel is None:
            return
        channel, self._channel = self._channel, None
        channel.close()
        try:
            self._process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()

    def __del__(self) -> None:
        if getattr(self, "_channel", None) is not None:
            with contextlib.suppress(Exception):  # at interpreter exit modules may be gone
                self.close()


def _die_with_parent(parent_pid: int) -> None:
    """Have the kernel kill this process when its parent dies (Linux ``PR_SET_PDEATHSIG``); exit
    at once if the parent is already gone."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent_pid:
        os._exit(0)


def _serve(channel: _Channel) -> None:
    """The child's loop: build the odometry, then answer calls until the parent hangs up (a
    parent gone mid-call ends it quietly)."""
    from frontends.odometry.base import make_odometry

    odometry: Odometry | None = None
    while True:
        try:
            method, argument = channel.receive()
        except (EOFError, ConnectionError):
            return
        try:
            if method == "build":
                name, options = argument
                odometry = make_odometry(name, **options)
                value = None
            elif method == "register":
                assert odometry is not None
                value = (odometry.register(argument), odometry.num_failures)
            elif method == "restart_covariance":
                assert odometry is not None
                value = odometry.restart_covariance()
            else:
                raise ValueError(f"unknown odometry call {method!r}")
        except Exception as exc:
            reply: tuple[str, Any] = ("error", exc)
        else:
            reply = ("ok", value)
        try:
            channel.send(reply)
        except ConnectionError:  # the parent hung up (Ctrl-C, SIGTERM): nobody to answer
            return


if __name__ == "__main__":
    # Ctrl-C and a SIGTERM of the process group reach this process too: the parent handles them
    # and closes the socket, which ends this process; a parent that dies takes it along
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    socket_fd, from_parent, to_parent, parent_pid = (int(arg) for arg in sys.argv[1:5])
    _die_with_parent(parent_pid)
    _serve(_Channel(Connection(socket_fd), _SharedFile(to_parent), _SharedFile(from_parent)))
