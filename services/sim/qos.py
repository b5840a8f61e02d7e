"""Why the simulator's streams travel as they do (declared on each Topic in contract.py: SMALL,
BULK) and `qos_for` for code that publishes one of those keys outside the simulator (benchmarks,
tests replaying a stream).

The small high-rate streams must not be lost behind the ~1 MB images and scans on the same link:
with zenoh's defaults (priority DATA, congestion control DROP) 5-10 % of IMU / clock / truth
samples were dropped, in bursts of up to ~90 ms, while frames were in flight. A higher priority
(DATA_HIGH) gives them their own queue ahead of the frames (the sensor stack test still gets
them at their rated stamp rates, within 5 %).
Congestion control stays DROP for every stream: BLOCK makes a publisher -- and the router
forwarding for it -- wait for its slowest subscriber. A ground station subscribing to
sim/truth/state across a saturated 20 Mbit/s link stalled the vehicle's router that way and
delayed its local deliveries by up to 1.3 s (planner -> fmu setpoint gaps up to 0.9 s; PX4 leaves
OFFBOARD after 1.0 s): nothing that may cross a link may block the vehicle's own loop
(tests/integration/test_multihost.py::test_saturated_link_never_stalls_the_vehicle). Only
service replies keep zenoh's BLOCK (services/runtime/node.py, Node.serve: a lost reply is worse).
Images and scans go at priority DATA_LOW: on a slow link to another host (radio, 20 Mbit/s) they
yield to state, goals and service replies; at DATA, 20 Hz raw frames starved a ground station's
arm request until it timed out (tests/integration/test_multihost.py::test_impaired_link).
"""
from __future__ import annotations

from aeroperception.services.runtime.wiring import zenoh_qos

from .contract import OUTPUTS

SMALL_STREAMS = tuple(k for k, t in OUTPUTS.declared.items() if t.qos.express and t.qos.priority == "data_high")
BULK_STREAMS = tuple(k for k, t in OUTPUTS.declared.items() if t.qos.bulk)   # thinned on a thin link


def qos_for(key: str) -> dict:
    """Keyword arguments for Node.publisher(key, ...): zenoh's, from the key's declaration."""
    t = OUTPUTS.declared.get(key)
    return zenoh_qos(t.qos) if t is not None else {}
