"""Fuzzing a live sim stack (slow): hypothesis-generated garbage on every key of every service's
contract INPUTS, on every queryable it serves (requests, action goals/cancel/result, parameter
@set), and random bytes on both MAVLink ports (fmu's FC link port, gcs's ground-station port),
while the vehicle hovers. Then: every service still alive (same pids, liveliness), each one
counted the invalid input in its diagnostics, no callback raised, zero unsafe
SET_POSITION_TARGET_LOCAL_NED at the FC (the tap checks every one), and the vehicle still holds
where it was (sim/truth/state).

Every payload sent on a key is checked to be invalid for the key's schema first (lenient decode
raises SchemaError), so a correct stack must drop all of them: valid-but-hostile motion
(NaN, 1000 m/s, 10 km away) is the last test, separately, as it needs fmu's envelope check.
"""
from __future__ import annotations

import importlib
import math
import socket
import time

import msgpack
import numpy as np
import pytest
from hypothesis import strategies as hs

from aeroperception.schemas import (
    REGISTRY, GcsLink, MissionStatus, SchemaError, TrajectorySetpoint, Vector3, VehicleState, decode, encode,
)
from aeroperception.services.runtime.node import encoding_for
from aeroperception.tools.cli.chaos import AT_REST_MPS
from aeroperception.tools.harness import poll_until, profile_services, speed
from faults.payloads import collect, garbage, mutated, schema_maps

# extended: 100 s; the schema fuzzers (unit) and every service's garbage tests stay in the default run.
pytestmark = [pytest.mark.slow, pytest.mark.extended, pytest.mark.timeout(280)]

PER_KEY = 200          # payloads published on each input key
PER_QUERYABLE = 30     # requests sent to each queryable
PER_PORT = 300         # datagrams sent to each MAVLink port
HOVER_ALT_M = 3.0


def service_contracts() -> dict[str, object]:
    """{service: contract module} for the profile's services that declare one."""
    out = {}
    for name in profile_services("sim"):
        try:
            out[name] = importlib.import_module(f"aeroperception.services.{name}.contract")
        except ModuleNotFoundError:
            continue
    return out


# Services whose inputs and queryables depend on how they were started, and that this stack starts
# without them: sim subscribes only with --follow (it flies its own vehicle here) and serves the
# camera models only while cameras render (--sensors none here).
STARTED_WITHOUT = {"sim"}


def input_keys(contracts) -> dict[str, tuple[type, list[str]]]:
    """{concrete key: (schema, [services subscribed])}; wildcards get a concrete chunk."""
    keys: dict[str, tuple[type, list[str]]] = {}
    for svc, c in contracts.items():
        if svc in STARTED_WITHOUT:
            continue
        for key, cls in getattr(c, "INPUTS", {}).items():
            key = key.replace("*", "fuzz")
            keys.setdefault(key, (cls, []))[1].append(svc)
    return keys


def queryables(contracts) -> dict[str, type | None]:
    """{key: request schema} of everything the services serve."""
    out: dict[str, type | None] = {}
    for svc, c in contracts.items():
        for key, (req, _reply) in getattr(c, "SERVICES", {}).items():
            if svc not in STARTED_WITHOUT:
                out[key] = req
        if svc == "mission":
            from aeroperception.schemas import ACTIONS, CancelRequest, ResultRequest

            for base in getattr(c, "ACTIONS", ()):
                out[f"{base}/goal"] = ACTIONS[base.rsplit("/", 1)[-1]].goal
                out[f"{base}/cancel"] = CancelRequest
                out[f"{base}/result"] = ResultRequest
        from aeroperception.schemas import ParamSet

        out[f"config/{svc}/@set"] = ParamSet
    return out


def invalid_for(cls: type, payloads: list[bytes]) -> list[bytes]:
    """Only the payloads that fail even lenient decoding as `cls` (a correct stack drops them all)."""
    out = []
    for p in payloads:
        try:
            decode(p, cls)
        except SchemaError:
            out.append(p)
    return out


def hostile_payloads(cls: type, n: int) -> list[bytes]:
    pack = lambda v: msgpack.packb(v, use_bin_type=True)  # noqa: E731
    strategy = hs.one_of(garbage(), mutated(cls), schema_maps(cls).map(pack))
    return invalid_for(cls, collect(strategy, n))


def counters(stack, services) -> dict[str, dict[str, int]]:
    out = {}
    for s in services:
        v = stack.diag(s).values
        out[s] = {"invalid": int(v.get("invalid_msgs", 0)), "callback_errors": int(v.get("callback_errors", 0)),
                  "bad_packets": int(v.get("bad_packets", 0))}
    return out


def hover(stack) -> VehicleState:
    if not stack.ensure_ground():
        stack.restart()
    r = stack.command("TAKEOFF")
    assert r.success, f"TAKEOFF refused: {r.message}"
    assert poll_until(lambda: stack.mission_state() == "HOLDING", 40, 0.3), f"not HOLDING: {stack.mission_state()}"
    rest = poll_until(lambda: (t := stack.truth()) is not None and speed(t) < 0.1 and t.position_m.z > 1.0 and t, 20, 0.3)
    assert rest, "vehicle did not settle into a hover"
    return rest


@pytest.fixture(scope="module")
def hovering(chaos_stack):
    hover(chaos_stack)
    return chaos_stack


def test_garbage_on_every_input_key_queryable_and_mavlink_port_is_counted_and_dropped(hovering):
    st = hovering
    contracts = {s: c for s, c in service_contracts().items() if s in st.services}   # those --sensors feeds
    services = list(contracts)
    keys = input_keys(contracts)
    served = queryables(contracts)
    pids0 = dict(st.pids())
    before = counters(st, services)
    t0 = time.monotonic()
    start = st.truth()
    link0 = st.latest("gcs/link", GcsLink, 3.0)
    rec = st.capture(truth=("sim/truth/state", VehicleState), status=("mission/status", MissionStatus))
    sent_per_service = {s: 0 for s in services}
    sent_keys = {}
    try:
        # 1. Data keys: hostile payloads with the key's own encoding (half) or none (half).
        for key, (cls, subscribers) in keys.items():
            payloads = hostile_payloads(cls, PER_KEY)
            pub = st.session.declare_publisher(key, encoding=encoding_for(cls))
            try:
                for i, p in enumerate(payloads):
                    if i % 2:
                        st.session.put(key, p)
                    else:
                        pub.put(p)
                    if i % 20 == 0:
                        time.sleep(0.005)
            finally:
                pub.undeclare()
            sent_keys[key] = len(payloads)
            for s in subscribers:
                sent_per_service[s] += len(payloads)
            # Wrong schema, honestly labelled: another type's valid message under this key.
            for other in ("Imu", "DiagnosticArray", "GcsLink"):
                ocls = REGISTRY[other]
                if ocls is not cls:
                    st.session.put(key, encode(ocls()), encoding=encoding_for(ocls))
        # 2. Queryables: garbage requests get a refusal, never an action.
        accepted, refused, unanswered, requests = [], 0, 0, 0
        for key, req in served.items():
            cls = req or REGISTRY["Empty"]
            payloads = hostile_payloads(cls, PER_QUERYABLE) if req is not None else collect(st_bytes(), PER_QUERYABLE)
            requests += len(payloads)
            for p in payloads:
                replies = list(st.session.get(key, payload=p, timeout=3.0))
                ok = [r.ok for r in replies if r.ok is not None]
                if not ok:
                    unanswered += 1
                    continue
                body = msgpack.unpackb(ok[0].payload.to_bytes(), strict_map_key=False)
                if isinstance(body, dict) and body.get("success") is True and req is not None:
                    accepted.append((key, p[:40]))
                else:
                    refused += 1
        # 3. MAVLink ports: random bytes, and valid frames cut or corrupted.
        datagrams = collect(hs.one_of(hs.binary(min_size=1, max_size=280), mavlink_mutations()), PER_PORT)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            for port in (st.fmu_port, st.gcs_port):
                for i, d in enumerate(datagrams):
                    sock.sendto(d, ("127.0.0.1", port))
                    if i % 20 == 0:
                        time.sleep(0.005)
        finally:
            sock.close()
        time.sleep(2.5)  # diagnostics are 1 Hz
        after = counters(st, services)
        link1 = st.latest("gcs/link", GcsLink, 3.0)
        end = st.truth()
        track = rec.since("truth", t0)
        status = rec.last("status")
    finally:
        rec.close()

    counted = {s: after[s]["invalid"] - before[s]["invalid"] for s in services}
    print(f"fuzz: {sum(sent_keys.values())} payloads on {len(sent_keys)} keys {sent_keys}")
    print(f"fuzz: sent per service {sent_per_service}; counted invalid {counted}")
    print(f"fuzz: {requests} requests on {len(served)} queryables: "
          f"{refused} refused, {len(accepted)} accepted, {unanswered} unanswered")
    print(f"fuzz: {len(datagrams)} datagrams to fmu and to gcs; fmu bad_packets "
          f"{before['fmu']['bad_packets']} -> {after['fmu']['bad_packets']}; gcs packets_invalid "
          f"{link0.packets_invalid if link0 else '?'} -> {link1.packets_invalid if link1 else '?'}")
    print(f"fuzz: unsafe setpoints at the FC {st.tap.unsafe_since(t0)[:3]} of {len(st.tap.setpoints_since(t0))}")
    # Alive, same processes (nothing crashed and was restarted).
    for s in services:
        assert st.alive(s), f"{s} not alive after the fuzzing"
        assert st.pids().get(s) == pids0.get(s), f"{s} restarted during the fuzzing (pid {pids0.get(s)} -> {st.pids().get(s)})"
    # Counted, not raised.
    for s, n in sent_per_service.items():
        if n:
            assert counted[s] >= 0.5 * n, f"{s}: {n} invalid payloads sent, {counted[s]} counted"
        assert after[s]["callback_errors"] == before[s]["callback_errors"], f"{s}: callbacks raised: {after[s]}"
    assert not accepted, f"garbage requests accepted: {accepted[:3]}"
    assert unanswered <= 0.02 * (refused + unanswered), f"{unanswered} garbage requests got no reply"
    assert after["fmu"]["bad_packets"] > before["fmu"]["bad_packets"] or after["fmu"]["invalid"] > before["fmu"]["invalid"]
    assert link1 is not None and link0 is not None and link1.packets_invalid > link0.packets_invalid
    # The FC saw nothing unsafe, and the vehicle still holds where it was.
    assert not st.tap.unsafe_since(t0), st.tap.unsafe_since(t0)[:5]
    drift = max(float(np.linalg.norm(m.position_m.to_array() - start.position_m.to_array())) for _, m in track)
    print(f"fuzz: hover drift {drift:.2f} m, end speed {speed(end):.2f} m/s, mission {status.state}")
    assert drift < 0.5, f"vehicle drifted {drift:.2f} m during the fuzzing"
    assert speed(end) < AT_REST_MPS and end.armed and end.position_m.z > 1.0
    assert status.state == "HOLDING", status.state


def st_bytes():
    return hs.binary(max_size=64)


def mavlink_mutations():
    """Valid MAVLink 2 frames (heartbeat, command, setpoint) with bytes flipped or cut."""
    from pymavlink.dialects.v20 import common as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frames = [
        mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0).pack(mav),
        mav.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0).pack(mav),
        mav.set_position_target_local_ned_encode(0, 1, 1, 1, 0, 0, 0, -3, 0, 0, 0, 0, 0, 0, 0, 0).pack(mav),
    ]

    def corrupt(args):
        frame, i, v, cut = args
        b = bytearray(frame)
        i = 10 + i % max(1, len(b) - 10)   # past the header: the CRC must fail
        b[i] = (b[i] + 1 + v) % 256
        return bytes(b[:max(1, len(b) - cut)])

    return hs.tuples(hs.sampled_from(frames), hs.integers(0, 300), hs.integers(0, 254), hs.integers(0, 3)).map(corrupt)


def test_hostile_setpoints_never_reach_the_fc(hovering):
    """Valid-schema but unsafe TrajectorySetpoints (NaN, inf, 1000 m/s, 10 km away) on
    fmu/in/trajectory_setpoint: fmu must refuse them and hold; the FC sees none."""
    st = hovering
    nan, inf = math.nan, math.inf
    hostile = [
        TrajectorySetpoint(position_valid=True, position_m=Vector3(x=nan, y=0.0, z=3.0)),
        TrajectorySetpoint(velocity_valid=True, velocity_mps=Vector3(x=inf, y=0.0, z=0.0)),
        TrajectorySetpoint(velocity_valid=True, velocity_mps=Vector3(x=1000.0, y=0.0, z=0.0)),
        TrajectorySetpoint(position_valid=True, position_m=Vector3(x=10_000.0, y=0.0, z=3.0)),
        TrajectorySetpoint(position_valid=True, position_m=Vector3(x=0.0, y=0.0, z=-50.0)),
    ]
    t0 = time.monotonic()
    start = st.truth()
    rec = st.capture(truth=("sim/truth/state", VehicleState))
    pub = st.session.declare_publisher("fmu/in/trajectory_setpoint", encoding=encoding_for(TrajectorySetpoint))
    try:
        for _ in range(10):   # 0.2 s of each at 50 Hz, interleaved with the planner's stream
            for sp in hostile:
                pub.put(encode(sp))
                time.sleep(0.004)
        time.sleep(2.0)
        track = rec.since("truth", t0)
    finally:
        pub.undeclare()
        rec.close()
    unsafe = st.tap.unsafe_since(t0)
    drift = max(float(np.linalg.norm(m.position_m.to_array() - start.position_m.to_array())) for _, m in track)
    print(f"hostile setpoints: {len(unsafe)} unsafe at the FC ({unsafe[:3]}), drift {drift:.2f} m")
    assert not unsafe, f"{len(unsafe)} unsafe setpoints reached the FC: {unsafe[:5]}"
    assert drift < 1.0, f"vehicle moved {drift:.2f} m"
