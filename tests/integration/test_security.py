"""Secured links: Zenoh TLS with client certificates, user/password login and the router's
access control (tools/secure/*.json5 = deploy/secure/, filled in by `aero certs`).

The role "ground" reads everything and calls mission services but its puts on fmu/in/** never
reach the vehicle; a client without credentials gets no session. Checked on 127.0.0.1 and across
two network namespaces (vehicle host with router + mission, ground host with the aero CLI).
Everything runs as real processes: `aero router`, `aero run mission`, `aero topic`/`service`."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from aerotest import aero_argv, clean_env, free_port
from netns import Follower, netns_unavailable

SETPOINT = '{"position_valid": true, "position_m": {"x": 1, "y": 2, "z": 3}}'
# A client session that must be refused; prints "open" or "refused <reason>".
PROBE = """
import json, sys, zenoh
conf = zenoh.Config.from_file(sys.argv[2]) if sys.argv[2] != "-" else zenoh.Config()
conf.insert_json5("mode", '"client"'); conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
for kv in sys.argv[3:]:
    k, v = kv.split("=", 1); conf.insert_json5(k, v)
try:
    zenoh.open(conf).close(); print("open")
except zenoh.ZError as e:
    print("refused", str(e).split(" at ")[0])
"""


class Local:
    """This machine, with the same interface as a netns.Host (popen/run/follow) for the checks."""

    def __init__(self):
        self.procs: list[subprocess.Popen] = []

    def popen(self, argv, **kw):
        kw.setdefault("stdin", subprocess.DEVNULL)
        p = subprocess.Popen(list(map(str, argv)), **kw)
        self.procs.append(p)
        return p

    def run(self, argv, timeout_s=30.0, **kw):
        kw.setdefault("capture_output", True)
        kw.setdefault("text", True)
        return subprocess.run(list(map(str, argv)), timeout=timeout_s, stdin=subprocess.DEVNULL, **kw)

    def follow(self, argv, **kw):
        kw.setdefault("stderr", subprocess.DEVNULL)
        return Follower(self.popen(argv, stdout=subprocess.PIPE, **kw))

    def stop_all(self):
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(8)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)


def make_certs(tmp: Path, hosts: list[str]) -> Path:
    out = tmp / "certs"
    args = ["certs", "--out", out] + [a for h in hosts for a in ("--host", h)]
    r = subprocess.run(aero_argv() + list(map(str, args)), capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stderr
    return out


def role_env(certs: Path | None, role: str | None, endpoint: str) -> dict[str, str]:
    """How a user points any aero command or service at the secured router: AERO_ZENOH_CONFIG."""
    env = clean_env(endpoint)
    if role:
        env["AERO_ZENOH_CONFIG"] = str(certs / f"{role}.json5")
    return env


def check_roles(vehicle, ground, certs: Path, router_listen: str, vehicle_ep: str, ground_ep: str, log: Path):
    """Start a secured `aero up` (router + mission) on `vehicle`, then exercise every role from `ground`."""
    # The documented production start: both configs in the environment, a TLS listen endpoint.
    env = dict(role_env(certs, "vehicle", None), AERO_ROUTER_CONFIG=str(certs / "router.json5"),
               AERO_STATE_DIR=str(log / "state"))
    with open(log / "aero-up.out", "w") as f:
        vehicle.popen(aero_argv() + ["up", "--only", "mission", "--listen", router_listen, "--log-dir", str(log / "up")],
                      stdout=f, stderr=subprocess.STDOUT, env=env)
    # The vehicle side's view of its setpoint input.
    seen = vehicle.follow(aero_argv() + ["topic", "echo", "fmu/in/trajectory_setpoint", "--json"],
                          env=role_env(certs, "vehicle", vehicle_ep))

    def call_get(role):
        return ground.run(aero_argv() + ["service", "call", "mission/srv/get", "--json", "--timeout", "3"],
                          env=role_env(certs, role, ground_ep))

    deadline = time.monotonic() + 30
    # (no mission loaded: the reply says success false, so the command exits 1 with the reply printed)
    while not (r := call_get("ground")).stdout.strip():   # the router and mission are starting
        assert time.monotonic() < deadline, f"ground never reached mission/srv/get: {r.stderr}\n" + \
            "".join(p.read_text() for p in [log / "aero-up.out", *sorted((log / "up").glob("*.log"))] if p.exists())
        time.sleep(0.5)
    reply = json.loads(r.stdout.splitlines()[0])
    assert reply["key"] == "mission/srv/get" and reply["schema"].startswith("GetMissionReply")

    def pub(role, marker: float):
        data = SETPOINT.replace('"z": 3', f'"z": {marker}')
        return ground.run(aero_argv() + ["topic", "pub", "fmu/in/trajectory_setpoint", "-t", "TrajectorySetpoint", data],
                          env=role_env(certs, role, ground_ep))

    time.sleep(1.0)  # the echo's subscription is declared
    # Positive control first: the same link and command with the vehicle role arrive...
    assert pub("vehicle", 7.0).returncode == 0
    seen.wait_for(lambda ln: '"z": 7.0' in ln, timeout_s=10)
    # ...the ground role's put is dropped at the router (its own publish call succeeds locally).
    t0 = time.monotonic()
    assert pub("ground", 9.0).returncode == 0
    assert pub("vehicle", 8.0).returncode == 0          # published after the ground's, arrives
    seen.wait_for(lambda ln: '"z": 8.0' in ln, timeout_s=10, since=t0)
    assert not any('"z": 9.0' in ln for _t, ln in seen.since(0)), "a ground setpoint reached the vehicle"

    # No credentials: no session, whichever way it tries.
    def probe(endpoint, config="-", *kv):
        return ground.run([sys.executable, "-c", PROBE, endpoint, str(config), *kv], timeout_s=30).stdout.strip()

    tcp = ground_ep.replace("tls/", "tcp/")
    assert probe(tcp).startswith("refused")                                   # plain TCP
    assert probe(ground_ep, "-", f'transport/link/tls/root_ca_certificate="{certs / "ca.pem"}"').startswith("refused")
    assert probe(ground_ep, certs / "ground.json5", 'transport/auth/usrpwd/password="guess"').startswith("refused")
    assert probe(ground_ep, certs / "ground.json5", "transport/auth/usrpwd={}").startswith("refused")
    assert probe(ground_ep, certs / "ground.json5") == "open"                 # the real credentials
    # The aero CLI says so in one line.
    r = ground.run(aero_argv() + ["topic", "echo", "state/vehicle", "--json"], env=clean_env(tcp), timeout_s=30)
    assert r.returncode != 0 and "Traceback" not in r.stderr and "no Zenoh router reachable" in r.stderr
    r = ground.run(aero_argv() + ["topic", "echo", "state/vehicle", "--json"], env=clean_env(ground_ep), timeout_s=30)
    assert r.returncode != 0 and "refused this client" in r.stderr and "AERO_ZENOH_CONFIG" in r.stderr


def test_secure_router_refuses_anonymous_and_ground_setpoints_on_loopback(tmp_path):
    if netns_unavailable() is None:
        pytest.skip("test_secure_router_across_hosts checks the same across network namespaces")
    port = free_port()
    certs = make_certs(tmp_path, ["localhost", "127.0.0.1"])
    here = Local()
    try:
        check_roles(here, here, certs, f"tls/127.0.0.1:{port}", f"tls/localhost:{port}",
                    f"tls/localhost:{port}", tmp_path)
    finally:
        here.stop_all()


def test_secure_router_across_hosts(lan, tmp_path):
    net = lan(["vehicle", "ground"])
    v, g = net["vehicle"], net["ground"]
    certs = make_certs(tmp_path, [v.addr, "127.0.0.1"])
    check_roles(v, g, certs, "tls/0.0.0.0:7447", "tls/127.0.0.1:7447", f"tls/{v.addr}:7447", tmp_path)
