"""Process shell of viz: subscribe to each adapter's key, sample, hand newest-wins to a worker
per slot, log to the viewer sink.

Every input goes through the adapter table (adapters.build_adapters): the contract's inputs are
bound to one table of handlers (`handlers()`), and each is bound when its rate is on, at start or
when a live change raises it from 0 (`bind_inputs`).

The Zenoh callbacks only compare a timestamp and swap a slot (microseconds, under node.lock);
conversion (JPEG, arrays) and Rerun logging run on the slot's worker. A worker still busy when a
newer sample arrives drops the older one (counted), and while the viewer is behind every new
sample is dropped (counted): viz may show less, never later, and never slows the stack.
"""
from __future__ import annotations

import functools
import time
from collections import Counter, deque

import numpy as np

from aeroperception.schemas import DiagnosticStatus, Empty, GetMissionReply, MissionStatus
from aeroperception.services.runtime import Health, LatestWorker, Service, run
from aeroperception.services.runtime.node import CallError

from . import contract
from .adapters import Adapter, build_adapters, mission_waypoints, static_scene
from .config import VizConfig
from .viewer import ViewerConfigError, ViewerSink


class FrameGate:
    """Stamps of the images sent to the viewer lately, so overlays (boxes) are drawn only on
    frames that are actually shown."""

    def __init__(self, keep: int = 64):
        self._stamps: dict[str, deque[int]] = {}
        self.keep = keep

    def note(self, key: str, stamp_ns: int) -> None:
        self._stamps.setdefault(key, deque(maxlen=self.keep)).append(stamp_ns)

    def admits(self, key: str, stamp_ns: int) -> bool:
        return stamp_ns in self._stamps.get(key, ())


class Sampler:
    """Per-slot minimum period from a rate parameter (wall time at arrival: it bounds CPU)."""

    def __init__(self):
        self._last: dict[str, float] = {}

    def admit(self, slot: str, rate_hz: float, now: float) -> bool:
        if rate_hz <= 0:
            return False
        last = self._last.get(slot)
        if last is not None and now - last < 1.0 / rate_hz:
            return False
        self._last[slot] = now
        return True


class VizService(Service):
    """Rerun live view of the stack: poses, tracks, cameras, clouds, costmap, mission, health."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = VizConfig

    def handlers(self) -> dict:
        """Every input to `_on_input` with its key: the adapter table decides what becomes of it."""
        return {t.handler_name: functools.partial(self._on_input, key) for key, t in contract.INPUTS.declared.items()}

    def bind_selection(self) -> dict:
        return {"inputs": ()}       # bound by start() and on_config(), as their rates turn on

    def start(self) -> None:
        p = self.cfg
        self.received: Counter[str] = Counter()
        self.sampled_out: Counter[str] = Counter()
        self.backlog_dropped: Counter[str] = Counter()
        self.logged: Counter[str] = Counter()
        self.work_ms: dict[str, deque[float]] = {}
        self.workers: dict[str, LatestWorker] = {}
        self.sampler = Sampler()
        self.frames = FrameGate()
        self.mission_id: str | None = None
        try:
            self.sink = ViewerSink(p.outputs, flush_timeout_s=p.flush_timeout_s, on_backlog=self._on_backlog)
        except ViewerConfigError as e:
            raise RuntimeError(f"viz: {e}") from None
        self.sink.write(self.node.now_ns() or time.time_ns(), static_scene())
        self.adapters = {ad.key: ad for ad in build_adapters(p)}
        self.subscribed: set[str] = set()
        self._subscribe_enabled(p)
        self.log.info("viewer", outputs=self.sink.describe())

    def on_config(self, cfg: VizConfig) -> None:
        self._subscribe_enabled(cfg)

    def _subscribe_enabled(self, cfg: VizConfig) -> None:
        """Subscribe each key whose rate is on. A key whose rate is 0 is not even subscribed (an
        image stream costs the router bandwidth); a live set that turns it on subscribes it then.
        Turned off again, it stays subscribed and the sampler drops everything."""
        keys = [k for k, ad in self.adapters.items()
                if k not in self.subscribed and (ad.rate_param is None or cfg.rate_hz(ad.rate_param) > 0)]
        if keys:
            self.bind_inputs(keys)
            self.subscribed.update(keys)

    def _on_backlog(self) -> None:
        self.log.warn("viewer_behind", note="dropping until it catches up")

    def stop(self) -> None:
        for w in list(self.workers.values()):
            w.stop(0.1)
        if hasattr(self, "sink"):
            self.sink.close(1.5)

    # ------------------------------------------------------------ Zenoh callbacks (cheap)

    def _on_input(self, key: str, msg) -> None:
        ad: Adapter = self.adapters[key]
        slot = ad.slot(msg) if ad.slot else ad.key
        self.received[slot] += 1
        if ad.key == "mission/status":
            self._check_mission(msg)
        if ad.truth and not self.cfg.show_truth:
            self.sampled_out[slot] += 1
            return
        stamp = msg.header.stamp_ns
        if ad.follows is not None:
            if not self.frames.admits(ad.follows, stamp):
                self.sampled_out[slot] += 1
                return
        elif ad.rate_param and not self.sampler.admit(slot, self.cfg.rate_hz(ad.rate_param), time.monotonic()):
            self.sampled_out[slot] += 1
            return
        if self.sink.backlogged:
            self.backlog_dropped[slot] += 1
            return
        if ad.schema.__schema_name__ == "Image":
            self.frames.note(ad.key, stamp)
        self._worker(slot, ad.convert).offer(msg)

    def _worker(self, slot: str, convert) -> LatestWorker:
        w = self.workers.get(slot)
        if w is None:
            w = self.workers[slot] = LatestWorker(functools.partial(self._write, slot, convert), f"viz-{slot}",
                                                  on_error=functools.partial(self._on_convert_error, slot))
        return w

    def _on_convert_error(self, slot: str, e: BaseException) -> None:
        self.log.throttled("error", f"viz:{slot}", "convert_failed", key=slot, error=f"{type(e).__name__}: {e}")

    def _check_mission(self, msg: MissionStatus) -> None:
        if msg.mission_id == self.mission_id:
            return
        self.mission_id = msg.mission_id
        self.node.call_async("mission/srv/get", Empty(), GetMissionReply, self._on_mission)

    def _on_mission(self, reply) -> None:
        if isinstance(reply, CallError):
            self.mission_id = None      # ask again with the next status
            return
        self._worker("mission/srv/get", mission_waypoints).offer(reply)

    # ------------------------------------------------------------ workers

    def _write(self, slot: str, convert, msg) -> None:
        t0 = time.perf_counter()
        logs = convert(msg)
        stamp = msg.header.stamp_ns if hasattr(msg, "header") else 0
        if logs:
            self.sink.write(stamp if stamp > 0 else (self.node.now_ns() or time.time_ns()), logs)
        self.logged[slot] += 1
        self.work_ms.setdefault(slot, deque(maxlen=100)).append((time.perf_counter() - t0) * 1e3)

    # ------------------------------------------------------------ diagnostics

    def health(self) -> Health:
        dropped = sum(w.dropped for w in self.workers.values())
        values: dict[str, object] = {
            "outputs": self.sink.describe(), "received": sum(self.received.values()),
            "logged": sum(self.logged.values()), "sampled_out": sum(self.sampled_out.values()),
            "dropped_busy": dropped, "dropped_viewer_behind": sum(self.backlog_dropped.values()),
            "viewer_behind_episodes": self.sink.backlog_episodes,
        }
        for slot, w in sorted(self.workers.items()):
            if w.dropped:
                values[f"dropped_busy[{slot}]"] = w.dropped
        for slot, d in sorted(self.work_ms.items()):
            if d:
                values[f"work_ms_p99[{slot}]"] = round(float(np.percentile(d, 99)), 2)
        if self.sink.backlogged:
            return Health(DiagnosticStatus.WARN, "viewer behind or absent: dropping new data", values)
        if not self.received:
            return Health(DiagnosticStatus.WARN, "nothing received yet", values)
        return Health(DiagnosticStatus.OK, f"streaming to {self.sink.describe()}", values)


def main(argv=None) -> int:
    return run(VizService, argv)
