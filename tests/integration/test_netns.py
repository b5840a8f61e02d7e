"""tests/netns.py itself: hosts reach each other only over their link, a pulled cable cuts them
off, netem delays them, and nothing outlives the Lan."""
from __future__ import annotations

import subprocess
import sys
import time

from aerotest import wait_until
from netns import netem_available

CONNECT = """
import socket, sys, time
t0 = time.monotonic()
try:
    s = socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=float(sys.argv[3]))
    s.sendall(b"x"); assert s.recv(1) == b"x"
    print(f"ok {(time.monotonic() - t0) * 1000:.1f}")
except OSError as e:
    print(f"fail {e}")
"""
ECHO = """
import socket
srv = socket.create_server(("0.0.0.0", 7000))
print("listening", flush=True)
while True:
    c, _ = srv.accept()
    c.sendall(c.recv(1)); c.close()
"""


def _connect(host, addr: str, timeout_s: float = 1.0) -> str:
    ip, _, port = addr.partition(":")
    return host.run([sys.executable, "-c", CONNECT, ip, port or "7000", str(timeout_s)], timeout_s=10).stdout.strip()


def test_hosts_link_cut_and_netem(lan):
    net = lan(["a", "b"])
    a, b = net["a"], net["b"]
    server = b.follow([sys.executable, "-u", "-c", ECHO])
    server.wait_for(lambda ln: ln == "listening", 10)
    assert _connect(a, b.addr).startswith("ok")
    assert _connect(a, "127.0.0.1").startswith("fail")      # a's own loopback: nothing listens there
    b.link(False)
    assert _connect(a, b.addr, 0.5).startswith("fail")
    b.link(True)
    assert _connect(a, b.addr, 3.0).startswith("ok")
    b.relay(7001, f"{b.addr}:7000", 50)                        # 50 ms each way: connect + echo >= 100 ms
    wait_until(lambda: _connect(a, b.addr + ":7001").startswith("ok") or None, 5, "relay up")
    ms = float(_connect(a, b.addr + ":7001", 3.0).split()[1])
    assert 95 <= ms < 400, ms
    b.impair(loss_pct=100)                                    # everything dropped in b
    assert _connect(a, b.addr, 0.5).startswith("fail")
    b.impair()
    assert _connect(a, b.addr, 3.0).startswith("ok")
    if netem_available():
        b.netem("delay 50ms")                                 # both ways: handshake + echo >= 2 RTT
        assert float(_connect(a, b.addr, 3.0).split()[1]) >= 190
        b.netem(None)
    names = [net.switch, a.ns, b.ns]
    net.close()
    assert server.proc.poll() is not None
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert not any(n in listed for n in names)


def test_namespaces_removed_after_a_failure(lan):
    net = lan(["x"])
    ns = net["x"].ns
    try:
        net["x"].run(["false"], check=True)
    except subprocess.CalledProcessError:
        pass
    net.close()
    time.sleep(0.1)
    assert ns not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
