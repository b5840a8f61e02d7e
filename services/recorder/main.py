"""Process shell: subscribe to the preset's keys, hand raw samples to the Recording, report health.

Its subscriptions are not its contract's: the preset's key expressions (any key, `**` included)
are taken raw (Node.subscribe_raw: no schema, no decoding) and recorded with each sample's own
encoding, so they cannot be contract Topics (a key and a schema). It declares CONTRACT all the
same, so Node.bind refuses an input or output it would grow by hand; its config is RecorderConfig.
"""
from __future__ import annotations

import json
import subprocess
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

import zenoh

from aeroperception.schemas import DiagnosticStatus, ParamList, SchemaError, decode
from aeroperception.services.runtime import Health, ParamError, Service, run

from . import contract
from .logic import KeyFilter, McapSink, Recording, RecorderConfig


def stack_version() -> str:
    """Package version plus the git commit when run from a checkout ("0.1.0+abc1234")."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("aeroperception")
    except PackageNotFoundError:
        v = "unknown"
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).parent,
                             capture_output=True, text=True, timeout=2).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        rev = ""
    return f"{v}+{rev}" if rev else v


DROP_WARN_S = 10.0   # WARN this long after the last dropped sample


class RecorderService(Service):
    """Record Zenoh keys to MCAP files (presets essentials/all, images on request)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = RecorderConfig

    @classmethod
    def add_arguments(cls, parser) -> None:
        parser.add_argument("--scenario", default="", help="scenario name for the file's metadata")

    def start(self) -> None:
        p = self.cfg
        self.exprs = p.key_exprs()
        cfg = p.sink
        try:
            cfg.check()
        except ValueError as e:
            raise ParamError(str(e)) from None
        meta = {"stack_version": stack_version(), "scenario": getattr(self.args, "scenario", "") or "",
                "vehicle": self.node.vehicle, "preset": p.preset, "keys": ",".join(self.exprs),
                "record_images": str(p.record_images).lower(),
                "started_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "clock": "sim" if self.node.clock and self.node.clock.is_sim else "wall"}
        self.recording = Recording(McapSink(cfg, {"aeroperception": meta}),
                                   int(p.max_buffer_mb * (1 << 20))).start()
        self.filter = KeyFilter(self.exprs, p.record_images)
        self._drops_seen, self._drop_at = 0, float("-inf")
        for i, expr in enumerate(self.exprs):
            self.node.subscribe_raw(self.node.key(expr), self._on_sample_for(i))
        self.log.info("recording", keys=self.exprs, output_dir=str(cfg.output_dir), max_bag_size=cfg.max_bag_size,
                      max_total_size=cfg.max_total_size or None)
        threading.Thread(target=self._record_params, name="recorder-params", daemon=True).start()

    def _on_sample_for(self, index: int):
        def on_sample(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            if self.filter.accept(index, key):
                self.recording.offer(key, str(sample.encoding), sample.payload.to_bytes(), self.node.now_ns())
        return on_sample

    def _record_params(self) -> None:
        """Every running service's parameters at start, one metadata record per service."""
        key = self.node.key("config/*/@params")
        try:
            replies = self.node.session.get(key, target=zenoh.QueryTarget.ALL,
                                            consolidation=zenoh.ConsolidationMode.NONE,
                                            timeout=self.cfg.params_timeout_s)
            for r in replies:
                if r.ok is None:
                    continue
                try:
                    plist = decode(r.ok.payload.to_bytes(), ParamList)
                except SchemaError:
                    continue
                self.recording.add_metadata(f"params/{plist.service}",
                                            {pd.name: json.dumps(pd.value) for pd in plist.params})
        except Exception as e:  # noqa: BLE001 - metadata is best effort, the recording goes on
            self.log.warn("params_not_recorded", error=str(e))

    def stop(self) -> None:
        self.recording.close()
        sink = self.recording.sink
        self.log.info("recording_closed", files=sink.stats.files, messages=sink.stats.messages,
                      dropped=self.recording.dropped, error=sink.error or None,
                      rotated_out=len(sink.stats.deleted) or None)

    def health(self) -> Health:
        sink = self.recording.sink
        values = {"messages": sink.stats.messages, "mbytes": round(sink.stats.bytes / 1e6, 2),
                  "files": len(sink.stats.files), "file": str(sink.path or ""),
                  "dropped": self.recording.dropped, "buffered_bytes": self.recording.buffer.bytes,
                  "before_clock": self.recording.before_clock,
                  "rotated_out_files": len(sink.stats.deleted),
                  "rotated_out_mbytes": round(sink.stats.deleted_bytes / 1e6, 2),
                  "rotation_errors": sink.stats.delete_errors,
                  "keys": ",".join(self.exprs)}
        if sink.failed:
            return Health(DiagnosticStatus.ERROR, f"recording stopped: {sink.error}", values)
        now = time.monotonic()
        if self.recording.dropped > self._drops_seen:
            self._drops_seen, self._drop_at = self.recording.dropped, now
        if now - self._drop_at < DROP_WARN_S:
            return Health(DiagnosticStatus.WARN, f"dropped {self.recording.dropped} samples (disk too slow)", values)
        return Health(DiagnosticStatus.OK, f"recording {len(sink.stats.per_key)} keys", values)


def main(argv=None) -> int:
    return run(RecorderService, argv)
