"""Test hosts as Linux network namespaces: several "machines" on one box, joined by a switch.

    from netns import Lan, netem_available, netns_unavailable

    reason = netns_unavailable()            # None, or why namespaces cannot be made (not root, no ip)
    with Lan(["vehicle", "ground"]) as lan:  # or the `lan` fixture in conftest.py
        v, g = lan["vehicle"], lan["ground"]
        v.addr                               # "10.77.0.2": the host's address on the LAN (g: .3, ...)
        p = v.popen(["aero", "up", "--listen", "tcp/0.0.0.0:7447"], stdout=f)   # Popen inside the host
        g.run(["ping", "-c1", v.addr])       # CompletedProcess (text, captured, bounded)
        f = g.follow(["aero", "topic", "echo", "state/vehicle", "--json"])
        f.wait_for(lambda line: '"armed"' in line, timeout_s=10)  # -> (monotonic time, line)
        v.link(False); v.link(True)          # pull / replug the host's cable (both ends down/up)
        v.netem("delay 50ms loss 2%")        # tc netem both ways (needs sch_netem: netem_available())
        v.impair(loss_pct=2, rate_kbit=2000) # no netem needed: nft random loss + tbf cap; impair() clears
        v.relay(7448, f"{v.addr}:7447", 50)  # TCP relay on v:7448 -> 7447 adding 50 ms each way
    # leaving the block: every process started through a host is stopped (SIGTERM, then SIGKILL),
    # then every namespace is deleted -- also when the test failed.

Each Lan has its own switch namespace (a bridge) and one namespace per host, linked by a veth
pair (host side `eth0`, switch side `p-<n>`); loopback is up in every host, so a whole `aero up`
stack runs inside one host on 127.0.0.1 as usual. Addresses are 10.77.0.0/24 and exist only inside
these namespaces (the switch has none); the test process's own namespace is never touched, so it
cannot talk to the hosts directly: run observers (`aero topic echo`, a probe script) inside a host.
Namespace names carry the test process's pid, so parallel runs never collide.
"""
from __future__ import annotations

import itertools
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterable, Sequence

from aeroperception.services.runtime.supervision import terminate

SUBNET = "10.77.0"          # /24, only inside the Lan's namespaces
_counter = itertools.count()


def netns_unavailable() -> str | None:
    """Why network namespaces cannot be made here (None when they can): tests skip with it."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "iproute2 (`ip`) is not installed"
    name = f"aero-probe-{os.getpid()}"
    r = subprocess.run(["ip", "netns", "add", name], capture_output=True, text=True)
    if r.returncode != 0:
        return f"ip netns add failed: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", name], capture_output=True)
    return None


def netem_available() -> bool:
    """Whether the kernel has sch_netem (`tc qdisc ... netem`); many VM kernels do not."""
    ns = f"aero-netem-{os.getpid()}"
    if _ip("netns", "add", ns, check=False).returncode != 0:
        return False
    try:
        return _tc(ns, "qdisc", "add", "dev", "lo", "root", "netem", "delay", "1ms", check=False).returncode == 0
    finally:
        _ip("netns", "del", ns, check=False)


def _tc(ns: str, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    r = subprocess.run(["ip", "netns", "exec", ns, "tc", *args], capture_output=True, text=True, timeout=10)
    if check and r.returncode != 0:
        raise RuntimeError(f"tc {' '.join(args)} in {ns}: {r.stderr.strip()}")
    return r


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    r = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
    if check and r.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {r.stderr.strip()}")
    return r


class Follower:
    """A process whose stdout lines are collected with their arrival time (time.monotonic())."""

    def __init__(self, proc: subprocess.Popen):
        self.proc = proc
        self.lines: list[tuple[float, str]] = []
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        for raw in self.proc.stdout:
            line = raw.decode(errors="replace").rstrip("\n") if isinstance(raw, bytes) else raw.rstrip("\n")
            with self._cond:
                self.lines.append((time.monotonic(), line))
                self._cond.notify_all()

    def since(self, t0: float) -> list[tuple[float, str]]:
        with self._cond:
            return [(t, ln) for t, ln in self.lines if t >= t0]

    def wait_for(self, pred: Callable[[str], bool], timeout_s: float = 10.0,
                 since: float = 0.0) -> tuple[float, str]:
        """The first line (arrived at or after `since`) satisfying pred, or AssertionError."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                for t, ln in self.lines:
                    if t >= since and pred(ln):
                        return t, ln
                left = deadline - time.monotonic()
                if left <= 0:
                    tail = "\n".join(ln for _, ln in self.lines[-5:])
                    raise AssertionError(f"no matching line within {timeout_s:.1f} s; last lines:\n{tail}")
                self._cond.wait(min(left, 0.2))


class Host:
    """One machine: a network namespace with loopback and `eth0` on the Lan."""

    def __init__(self, lan: "Lan", name: str, index: int):
        self.lan, self.name, self.index = lan, name, index
        self.ns = f"{lan.prefix}-{name}"
        self.addr = f"{SUBNET}.{index + 2}"
        self.port = f"p-{index}"            # its cable's switch-side end
        self.procs: list[subprocess.Popen] = []

    def argv(self, argv: Sequence[str]) -> list[str]:
        """`argv` run inside this host (ip netns exec execs it: the pid is the command's own)."""
        return ["ip", "netns", "exec", self.ns, *map(str, argv)]

    def popen(self, argv: Sequence[str], **kw) -> subprocess.Popen:
        """Start a process inside the host; stopped when the Lan closes if still running."""
        kw.setdefault("stdin", subprocess.DEVNULL)
        p = subprocess.Popen(self.argv(argv), **kw)
        self.procs.append(p)
        return p

    def run(self, argv: Sequence[str], timeout_s: float = 30.0, **kw) -> subprocess.CompletedProcess:
        kw.setdefault("capture_output", True)
        kw.setdefault("text", True)
        kw.setdefault("stdin", subprocess.DEVNULL)
        return subprocess.run(self.argv(argv), timeout=timeout_s, **kw)

    def follow(self, argv: Sequence[str], **kw) -> Follower:
        """Start a process inside the host and collect its stdout lines (stderr to DEVNULL unless given)."""
        kw.setdefault("stderr", subprocess.DEVNULL)
        return Follower(self.popen(argv, stdout=subprocess.PIPE, **kw))

    def link(self, up: bool) -> None:
        """Plug (True) or pull (False) this host's cable: both ends of its veth go up/down."""
        state = "up" if up else "down"
        _ip("-n", self.lan.switch, "link", "set", self.port, state)
        _ip("-n", self.ns, "link", "set", "eth0", state)

    def netem(self, spec: str | None) -> None:
        """`tc netem` on both directions of this host's link, e.g. "delay 50ms loss 2%"; None clears.
        Needs sch_netem in the kernel (netem_available()); else use impair() and relay()."""
        for ns, dev in ((self.ns, "eth0"), (self.lan.switch, self.port)):
            _tc(ns, "qdisc", "del", "dev", dev, "root", check=False)
            if spec:
                _tc(ns, "qdisc", "add", "dev", dev, "root", "netem", *spec.split())

    def impair(self, loss_pct: float = 0.0, rate_kbit: int | None = None) -> None:
        """Kernel impairments that need no netem: random loss of `loss_pct` % of the packets in each
        direction (nftables numgen in this host) and a bandwidth cap (tbf on both ends of its link).
        impair() with no arguments clears both."""
        subprocess.run(["ip", "netns", "exec", self.ns, "nft", "delete", "table", "inet", "aeroimpair"],
                       capture_output=True, timeout=10)
        for ns, dev in ((self.ns, "eth0"), (self.lan.switch, self.port)):
            _tc(ns, "qdisc", "del", "dev", dev, "root", check=False)
            if rate_kbit:
                _tc(ns, "qdisc", "add", "dev", dev, "root", "tbf", "rate", f"{int(rate_kbit)}kbit",
                    "burst", "32kbit", "latency", "200ms")
        if loss_pct > 0:
            per_10k = int(round(loss_pct * 100))
            rules = (f"table inet aeroimpair {{\n"
                     f" chain in {{ type filter hook input priority 0; iifname \"eth0\" numgen random mod 10000 <= {min(per_10k, 10000) - 1} drop; }}\n"
                     f" chain out {{ type filter hook output priority 0; oifname \"eth0\" numgen random mod 10000 <= {min(per_10k, 10000) - 1} drop; }}\n"
                     f"}}\n")
            r = subprocess.run(["ip", "netns", "exec", self.ns, "nft", "-f", "-"], input=rules,
                               capture_output=True, text=True, timeout=10)
            if r.returncode != 0:
                raise RuntimeError(f"nft loss {loss_pct} % on {self.name}: {r.stderr.strip()}")

    def relay(self, listen_port: int, target: str, delay_ms: float | str) -> subprocess.Popen:
        """A TCP relay inside this host: connections to <addr>:listen_port reach `target`
        ("ADDR:PORT") with every chunk held `delay_ms` each way -- link latency for kernels without
        netem (a TCP-level delay: what a Zenoh link over a slow radio sees). delay_ms "@FILE": the
        delay is read from FILE (a number, re-read every 0.2 s) so a test can change it live.
        Stopped with the Lan."""
        return self.popen([sys.executable, "-u", __file__, "relay", str(listen_port), target, str(delay_ms)],
                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def stop_all(self, timeout_s: float = 8.0) -> None:
        """SIGTERM every process started here, wait (bounded), SIGKILL what is left."""
        terminate(self.procs, timeout_s)


class Lan:
    """Hosts on one switch. Use as a context manager (or call close()): namespaces never outlive it."""

    def __init__(self, names: Iterable[str]):
        self.prefix = f"aero{os.getpid()}n{next(_counter)}"
        self.switch = f"{self.prefix}-switch"
        self.hosts: dict[str, Host] = {}
        self._made: list[str] = []
        try:
            self._build(list(names))
        except BaseException:
            self.close()
            raise

    def _build(self, names: list[str]) -> None:
        if len(names) > 200:
            raise ValueError("at most 200 hosts")
        _ip("netns", "add", self.switch)
        self._made.append(self.switch)
        _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.switch, "link", "set", "br0", "up")
        for i, name in enumerate(names):
            h = Host(self, name, i)
            _ip("netns", "add", h.ns)
            self._made.append(h.ns)
            _ip("link", "add", "eth0", "netns", h.ns, "type", "veth", "peer", "name", h.port, "netns", self.switch)
            _ip("-n", self.switch, "link", "set", h.port, "master", "br0")
            _ip("-n", self.switch, "link", "set", h.port, "up")
            _ip("-n", h.ns, "link", "set", "lo", "up")
            _ip("-n", h.ns, "addr", "add", f"{h.addr}/24", "dev", "eth0")
            _ip("-n", h.ns, "link", "set", "eth0", "up")
            self.hosts[name] = h

    def __getitem__(self, name: str) -> Host:
        return self.hosts[name]

    def __enter__(self) -> "Lan":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop every process started through a host, then delete every namespace (idempotent)."""
        for h in self.hosts.values():
            h.stop_all()
        for ns in reversed(self._made):
            _ip("netns", "del", ns, check=False)
        self._made.clear()


# ---------------------------------------------------------------- delay relay (run as a script)


QUEUE_BYTES = 256 * 1024   # the relay's backlog per direction before it stops reading
# The relay's own kernel buffers, fixed: autotuned they grew to ~1 MB towards a capped link (0.5 s
# at 20 Mbit/s) -- a queue no direct link has, which would hide what the endpoints' settings do.
SOCKET_BYTES = 64 * 1024


def _relay_main(listen_port: int, target: str, delay_spec: str) -> None:
    """Accept TCP connections and pipe each to `target`, every chunk delivered the delay later
    (order kept; one thread per direction)."""
    import collections
    import socket

    delay_s = [0.0]

    def read_delay() -> None:
        while True:
            try:
                delay_s[0] = float(Path(delay_spec[1:]).read_text().strip() or 0) / 1000.0
            except (OSError, ValueError):
                pass
            time.sleep(0.2)

    if delay_spec.startswith("@"):
        threading.Thread(target=read_delay, daemon=True).start()
    else:
        delay_s[0] = float(delay_spec) / 1000.0
    host, port = target.rsplit(":", 1)
    srv = socket.create_server(("0.0.0.0", listen_port))

    def pipe(src: socket.socket, dst: socket.socket) -> None:
        q: collections.deque = collections.deque()
        cond = threading.Condition()
        done: list = []
        queued = [0]

        def sender() -> None:
            while True:
                with cond:
                    while not q and not done:
                        cond.wait()
                    if not q:
                        break
                    due, data = q.popleft()
                    queued[0] -= len(data)
                    cond.notify_all()
                time.sleep(max(0.0, due - time.monotonic()))
                try:
                    dst.sendall(data)
                except OSError:
                    break
            try:
                dst.shutdown(socket.SHUT_WR)
            except OSError:
                pass

        t = threading.Thread(target=sender, daemon=True)
        t.start()
        while True:
            try:
                data = src.recv(65536)
            except OSError:
                data = b""
            with cond:
                if not data:
                    done.append(True)
                    cond.notify_all()
                    break
                q.append((time.monotonic() + delay_s[0], data))
                queued[0] += len(data)
                cond.notify_all()
                # Bounded like a real link's buffers: stop reading until the backlog drains, so
                # the sender's own queues (zenoh's priority queues) fill and decide what waits.
                while queued[0] > QUEUE_BYTES and not done:
                    cond.wait(0.5)

    while True:
        c, _ = srv.accept()
        try:
            u = socket.create_connection((host, int(port)), timeout=5)
        except OSError:
            c.close()
            continue
        u.settimeout(None)
        for a, b in ((c, u), (u, c)):
            a.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            a.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BYTES)
            a.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BYTES)
            threading.Thread(target=pipe, args=(a, b), daemon=True).start()


if __name__ == "__main__" and len(sys.argv) == 5 and sys.argv[1] == "relay":
    _relay_main(int(sys.argv[2]), sys.argv[3], sys.argv[4])
