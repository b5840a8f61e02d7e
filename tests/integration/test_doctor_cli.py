"""`aero doctor` as a user runs it, on this machine: one line per check, every service of the
profile importable here (every extra is installed), and the exit code 1 exactly when a check
FAILs: here a TCP port this test holds, given as the router's."""
from __future__ import annotations

import re
import socket

from aerotest import aero, free_port, free_udp_port

from aeroperception.tools.harness import profile_services

LINE = re.compile(r"^(ok  |warn|FAIL)  \S.*$")


def lines_of(out: str) -> tuple[list[str], str]:
    *checks, summary = out.strip().splitlines()
    bad = [ln for ln in checks if not LINE.match(ln)]
    assert not bad, bad
    return checks, summary


def test_doctor_on_this_machine_passes_with_free_ports():
    port = free_port()
    listen = f"tcp/127.0.0.1:{port}"
    r = aero("doctor", "--listen", listen, "--port", f"tcp:{port}", "--port", f"udp:{free_udp_port()}", timeout_s=90)
    checks, summary = lines_of(r.stdout)
    assert r.returncode == 0, r.stdout + r.stderr
    for s in profile_services("sim"):
        assert f"ok    {s}: imports found (" in r.stdout, (s, r.stdout)
    assert f"router: none at {listen}" in r.stdout
    assert any(ln.startswith(("ok    PX4:", "warn  PX4:")) for ln in checks)      # sim: never FAIL for PX4
    assert any(ln.startswith(("ok    Docker:", "warn  Docker:")) for ln in checks)
    assert any("onnxruntime" in ln and "providers: CPU yes" in ln for ln in checks)
    assert sum(ln.startswith("ok    clock:") or ln.startswith("warn  clock:") for ln in checks) == 3
    assert summary.startswith("aero doctor: profile sim: 0 FAIL,"), summary


def test_doctor_fails_on_a_port_in_use():
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen(1)
        port = held.getsockname()[1]
        r = aero("doctor", "--profile", "vehicle", "--listen", f"tcp/127.0.0.1:{port}", "--port", f"tcp:{port}",
                 timeout_s=90)
    checks, summary = lines_of(r.stdout)
    assert r.returncode == 1, r.stdout + r.stderr
    assert [ln for ln in checks if ln.startswith("FAIL")] == [
        f"FAIL  port tcp 127.0.0.1:{port}, given with --port: in use -> stop what holds it "
        f"(`ss -tlnp | grep :{port}` shows it: another aero up, PX4 or ground station?)"]
    # something listens there, but it is no Zenoh router: said, not failed
    assert any(ln.startswith(f"warn  router: something listens at tcp/127.0.0.1:{port}") for ln in checks)
    assert "1 FAIL" in summary
