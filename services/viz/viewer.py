"""Where the Rerun stream goes (native viewer, a viewer elsewhere, the web viewer + gRPC served
from the vehicle, a .rrd file) and the default layout, so the first view is useful.

`ViewerSink` owns one RecordingStream. Logging never waits on a viewer: `log()` hands data to
Rerun's own batcher, and a watchdog thread flushes with a timeout; when a viewer falls behind
(or is absent) `backlogged` is set and the service drops new data until it catches up, instead
of letting Rerun buffer without bound.
"""
from __future__ import annotations

import socket
import threading
import time
import uuid
from dataclasses import dataclass

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from aeroperception.services.runtime import param

from .adapters import TIMELINE, WORLD, Log


class ViewerConfigError(ValueError):
    """The parameters name no output, or an unusable one."""


def default_blueprint() -> rrb.Blueprint:
    """3D scene (ENU) with both cameras below it; altitude, speed, battery, loop timing and the
    text logs (mission, safety, diagnostics) on the right."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin=WORLD, name="Scene (ENU)"),
                rrb.Horizontal(rrb.Spatial2DView(origin="camera/left", name="Left camera"),
                               rrb.Spatial2DView(origin="camera/right", name="Right camera")),
                row_shares=[3, 2]),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="series/altitude_m", name="Altitude (m)"),
                rrb.TimeSeriesView(origin="series/speed_mps", name="Speed (m/s)"),
                rrb.TimeSeriesView(origin="series/battery_pct", name="Battery (%)"),
                rrb.TimeSeriesView(origin="series/loop_work_p99_ms", name="Loop work p99 (ms)"),
                rrb.TextLogView(origin="logs", name="Mission, safety, diagnostics")),
            column_shares=[3, 2]),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed"),
    )


@dataclass(frozen=True)
class Outputs:
    """Where the view goes: the parameters of the same names (see contract.PARAMS)."""

    web_port: int = param("web_port")
    grpc_port: int = param("grpc_port")
    serve_grpc: bool = param("serve_grpc")
    bind_ip: str = param("bind_ip")
    server_memory_limit: str = param("server_memory_limit")
    viewer_url: str = param("viewer_url")
    spawn: bool = param("spawn")
    save_path: str = param("save_path")

    @property
    def serving(self) -> bool:
        return self.web_port > 0 or self.serve_grpc

    def check(self) -> None:
        if not (self.serving or self.viewer_url or self.spawn or self.save_path):
            raise ViewerConfigError("no output: set web_port, serve_grpc, viewer_url, spawn or save_path")
        if self.viewer_url and not self.viewer_url.startswith(("rerun://", "rerun+http://", "rerun+https://")):
            raise ViewerConfigError(f"viewer_url {self.viewer_url!r}: expected rerun+http://HOST:PORT/proxy")
        if self.serving and not self.grpc_port:
            raise ViewerConfigError("web_port / serve_grpc need a grpc_port")


def public_host(bind_ip: str) -> str:
    return socket.gethostname() if bind_ip in ("0.0.0.0", "::") else bind_ip


class ViewerSink:
    def __init__(self, out: Outputs, application_id: str = "aeroperception", flush_timeout_s: float = 0.5,
                 on_backlog=None):
        out.check()
        self.out = out
        self.flush_timeout_s = flush_timeout_s
        self.on_backlog = on_backlog
        self.rec = rr.RecordingStream(application_id, recording_id=uuid.uuid4())
        self.grpc_uri = ""
        self.web_url = ""
        self.backlogged = False
        self.backlog_episodes = 0
        sinks: list = []
        if out.save_path:
            sinks.append(rr.FileSink(out.save_path))
        if out.serving:
            # newest_first: a viewer that connects mid-flight shows "now" at once, history fills in.
            server = rr.GrpcServerSink(out.bind_ip, out.grpc_port, server_memory_limit=out.server_memory_limit,
                                       newest_first=True)
            sinks.append(server)
            self.grpc_uri = f"rerun+http://{public_host(out.bind_ip)}:{out.grpc_port}/proxy"
        if out.spawn:
            port = out.grpc_port + 1 if out.serving else out.grpc_port
            # recording=: without it rr.spawn looks for a global recording, finds none (ours is
            # our own stream) and only logs "Rerun is disabled - spawn() call ignored".
            rr.spawn(port=port, connect=False, hide_welcome_screen=True, recording=self.rec)
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy"))
        if out.viewer_url:
            sinks.append(rr.GrpcSink(out.viewer_url))
        self.rec.set_sinks(*sinks, default_blueprint=default_blueprint())
        if out.web_port:
            rr.serve_web_viewer(web_port=out.web_port, open_browser=False)
            host = public_host(out.bind_ip)
            self.web_url = f"http://{host}:{out.web_port}/?url={self.grpc_uri.replace('+', '%2B')}"
        self._stop = threading.Event()
        self._watchdog = threading.Thread(target=self._watch, name="viz-flush", daemon=True)
        self._watchdog.start()

    def describe(self) -> str:
        parts = []
        if self.web_url:
            parts.append(f"web {self.web_url}")
        elif self.grpc_uri:
            parts.append(f"gRPC {self.grpc_uri}")
        if self.out.spawn:
            parts.append("native viewer")
        if self.out.viewer_url:
            parts.append(f"viewer {self.out.viewer_url}")
        if self.out.save_path:
            parts.append(f"file {self.out.save_path}")
        return ", ".join(parts)

    def write(self, stamp_ns: int, logs: list[Log]) -> None:
        """Log at `stamp_ns` on the shared timeline (thread-local time: safe from any worker)."""
        self.rec.set_time(TIMELINE, timestamp=np.datetime64(int(stamp_ns), "ns"))
        for entry in logs:
            self.rec.log(entry.path, *entry.archetypes, static=entry.static)

    def _watch(self) -> None:
        while not self._stop.wait(0.5):
            try:
                self.rec.flush(timeout_sec=self.flush_timeout_s)
                self.backlogged = False
            except Exception:  # noqa: BLE001 - Rerun says "flush timed out": the viewer is behind
                if not self.backlogged:
                    self.backlog_episodes += 1
                    if self.on_backlog:
                        self.on_backlog()
                self.backlogged = True

    def close(self, timeout_s: float = 1.5) -> None:
        """Finish the .rrd (footer) within the stop budget. With a viewer that is absent or behind,
        Rerun waits for it (2 s to finalize the file, 5 s to drop a gRPC client): that runs on a
        daemon thread we stop waiting for, and the file, if its footer is then missing, is still
        a valid stream (rerun.chunk.RrdReader(path).stream(), `rerun rrd optimize`)."""
        deadline = time.monotonic() + timeout_s
        self._stop.set()
        self._watchdog.join(max(0.05, deadline - time.monotonic()))

        def finish() -> None:
            if not self.backlogged:
                try:
                    self.rec.flush(timeout_sec=max(0.05, deadline - time.monotonic()))
                except Exception:  # noqa: BLE001 - a viewer that fell behind just now
                    pass
            if self.out.save_path:
                rr.bindings.finalize_deferred_sinks(recording=self.rec.to_native())
            self.rec.disconnect()

        t = threading.Thread(target=finish, name="viz-close", daemon=True)
        t.start()
        t.join(max(0.05, deadline - time.monotonic()))
