"""Where a recording goes: an ``.rrd`` file, a spawned viewer, a running viewer, or a served one.

Serving hosts a gRPC server (``rr.GrpcServerSink``, which buffers the whole recording for late
viewers) and Rerun's web viewer over HTTP (:class:`~slam.app.web_viewer.WebViewerServer`), both
bound to the given address.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from slam.app.web_viewer import WebViewerServer, viewer_executable

SPAWN_PORT = 9876
"""The gRPC port of a spawned local viewer."""


def open_recording(
    application_id: str,
    rrd_path: Path | None,
    spawn: bool,
    connect_url: str | None,
    serve_port: int | None,
    web_port: int,
    serve_bind_ip: str,
    blueprint: Any,
) -> tuple[Any, WebViewerServer | None]:
    """A ``rr.RecordingStream`` sending to every sink asked for, and the web viewer serving it
    (None unless ``serve_port``); ``blueprint`` is the default blueprint of every sink."""
    import rerun as rr

    rec = rr.RecordingStream(application_id)
    sinks: list[object] = []
    if rrd_path is not None:
        rrd_path.parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(rrd_path)))
    if spawn:
        rr.spawn(port=SPAWN_PORT, connect=False, recording=rec, executable_path=viewer_executable())
        sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{SPAWN_PORT}/proxy"))
    if connect_url is not None:
        sinks.append(rr.GrpcSink(connect_url))
    server = None
    if serve_port is not None:
        server = rr.GrpcServerSink(bind_ip=serve_bind_ip, port=int(serve_port))
        sinks.append(server)
    rec.set_sinks(*sinks, default_blueprint=blueprint)
    if server is None:
        return rec, None
    # not rr.serve_web_viewer: it listens on every interface
    return rec, WebViewerServer(serve_bind_ip, int(web_port), server.uri)
