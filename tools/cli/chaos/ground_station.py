"""A ground station stand-in for the ground-station-loss row: MAV_TYPE_GCS heartbeats to gcs, then
silence when stopped."""
from __future__ import annotations

import select
import socket
import threading

from pymavlink.dialects.v20 import common as mavlink


class FakeGcs:
    """A ground station on a UDP socket: MAV_TYPE_GCS heartbeats to gcs at 1 Hz until stopped."""

    def __init__(self, gcs_port: int, system_id: int = 255):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.target = ("127.0.0.1", gcs_port)
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=mavlink.MAV_COMP_ID_MISSIONPLANNER)
        self.stop_ev = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop_ev.is_set():
            hb = self.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            try:
                self.sock.sendto(hb.pack(self.mav), self.target)
                while select.select([self.sock], [], [], 0)[0]:
                    self.sock.recv(65535)   # telemetry from gcs: drain
            except OSError:
                pass
            self.stop_ev.wait(1.0)

    def stop(self) -> None:
        self.stop_ev.set()
        self.thread.join(2.0)
        self.sock.close()
