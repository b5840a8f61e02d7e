"""The stack split across two machines (network namespaces, tests/netns.py) joined by one link.

vehicle host 10.77.0.2: `aero up --only sim,fmu,planner,safety --listen tcp/0.0.0.0:7447 --thin-link eth0`
ground host 10.77.0.3:  `aero up --only mission,gcs --connect tcp/10.77.0.2:7448` (its own router
                        joins the vehicle's), the `aero` CLI, and an observer (tests/netprobe.py)
The ground reaches the vehicle's router through a TCP relay on the vehicle host (port 7448, to
10.77.0.2:7447, so the router sees the link on eth0) whose delay the impairment tests set (this
kernel has no sch_netem); loss is nftables on the vehicle's eth0, the bandwidth cap tbf.

- test_mission_across_the_link (slow): `aero mission fly` on the ground flies takeoff, goto, land.
- test_link_cut_mid_flight (slow): the cable is pulled for 5 s on a 40 m leg. Vehicle side: the
  planner flies on for goal_timeout_s (2 s without the mission's 2 Hz goal) and then holds where
  it is; fmu streams setpoints throughout, the FC stays in OFFBOARD, no process restarts. Ground side: the mission sees state/vehicle go stale (fmu outage rule) and
  goes HOLDING; when the link is back its hold goal reaches the planner, the vehicle stops and
  holds (ARCHITECTURE §8: stale motion is never replayed, the mission decides), every vehicle key
  reaches the ground again within 5 s, and a LAND from the ground lands it.
- test_impaired_link (extended): 50 ms each way + 2 % loss each way: the lean mission flies from the ground.
- test_saturated_link_never_stalls_the_vehicle (slow): the same link capped at 20 Mbit/s and 20 Hz
  raw 640x480 frames (147 Mbit/s) the ground follows: the vehicle's 50 Hz setpoint stream never
  gaps, frames arrive sampled; on the camera key (--thin-link: 1 Hz) state/vehicle stays fresh on
  the ground.
Figures are printed (pytest -s) for docs/results/benchmarks.md and the issue.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import statistics
import sys
import time
from pathlib import Path

import pytest

from aerotest import aero_argv, wait_until

REPO = Path(__file__).resolve().parents[2]
PROBE = REPO / "tests" / "netprobe.py"
VEHICLE_SERVICES = ["sim", "fmu", "planner", "safety"]
GROUND_SERVICES = ["mission", "gcs"]
# What the ground must see again after a cut: every vehicle-side stream it follows.
VEHICLE_KEYS = ["state/vehicle", "sim/truth/state", "planner/status", "safety/status", "fmu/out/vehicle_status",
                "diagnostics/sim", "diagnostics/fmu", "diagnostics/planner", "diagnostics/safety"]
BULK = "test/bulk"   # 640x480 frames on a key no --thin-link rule covers: they do fill the link
GROUND_KEYS = VEHICLE_KEYS + ["mission/status", "sensors/camera/left/image", BULK]
CUT_S = 5.0
RATE_KBIT = 20_000    # the impaired link's cap: 20 Mbit/s, a seventh of what 20 Hz raw 640x480 needs
RECOVERY_LIMIT_S = 5.0
LEAN = {"mission_id": "lean", "takeoff_altitude_m": 3.0, "waypoint_acceptance_radius_m": 0.5,
        "waypoints": [{"x": 0.0, "y": 0.0, "z": 3.0, "yaw_deg": 0.0}, {"x": 6.0, "y": 0.0, "z": 3.0, "yaw_deg": 0.0}]}
LONG_LEG = {"mission_id": "long_leg", "takeoff_altitude_m": 4.0, "waypoint_acceptance_radius_m": 0.5,
            "waypoints": [{"x": 0.0, "y": 0.0, "z": 4.0, "yaw_deg": 0.0}, {"x": 40.0, "y": 0.0, "z": 4.0, "yaw_deg": 0.0}]}
IMAGES = """
import sys, time, numpy as np
from aeroperception.schemas import Header, Image, NDArray
from aeroperception.services.runtime import Node
from aeroperception.services.sim.qos import qos_for
node = Node("image_source", connect=sys.argv[1], log_level="warn")
assert node.connect(max_wait_s=10)
pub = node.publisher(sys.argv[2], Image, **qos_for("sensors/camera/left/image"))  # the sim's camera QoS
frame = NDArray.from_numpy(np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8))
t = time.monotonic()
while True:
    pub.publish(Image(header=Header(stamp_ns=time.time_ns(), frame_id="cam"), height=480, width=640, data=frame))
    t += 0.05
    time.sleep(max(0.0, t - time.monotonic()))
"""


GROUND_ENV: dict[str, str] = {}   # AERO_ZENOH_CONFIG for every ground process (set by Hosts)


class Observer:
    """tests/netprobe.py inside a host, parsed: samples per key with receive times."""

    def __init__(self, host, keys: list[str]):
        env = _env() if host.name == "ground" else None
        self.f = host.follow([sys.executable, "-u", str(PROBE), "--connect", "tcp/127.0.0.1:7447", *keys], env=env)
        self.f.wait_for(lambda ln: '"ready"' in ln, 30)

    def records(self, since: float = 0.0) -> list[tuple[float, dict]]:
        out = []
        for t, ln in self.f.since(since):
            try:
                out.append((t, json.loads(ln)))
            except ValueError:
                pass
        return out

    def samples(self, key: str, since: float = 0.0, until: float = float("inf")) -> list[tuple[float, dict]]:
        return [(t, r) for t, r in self.records(since) if r.get("k") == key and t <= until]

    def last(self, key: str) -> dict | None:
        s = self.samples(key)
        return s[-1][1].get("d") if s else None

    def alive(self) -> set[str]:
        state: dict[str, bool] = {}
        for _t, r in self.records():
            if "alive" in r:
                state[r["alive"].rsplit("/", 1)[-1]] = r["put"]
        return {k for k, v in state.items() if v}


def _up(host, log_dir: Path, only: list[str], extra: list[str]):
    log_dir.mkdir(parents=True, exist_ok=True)
    out = open(log_dir / "aero-up.out", "wb")
    env_argv = ["env", f"AERO_STATE_DIR={log_dir / 'state'}", "PYTHONUNBUFFERED=1",
                *(f"{k}={v}" for k, v in (GROUND_ENV.items() if host.name == "ground" else ()))]
    return host.popen(env_argv + aero_argv() + ["up", "--only", ",".join(only), "--log-dir", str(log_dir),
                                                *extra], stdout=out, stderr=subprocess.STDOUT)


def _ground_config(base: Path) -> Path:
    """zenoh.json5 with shared memory off: on one test machine both hosts could map the same
    /dev/shm and large payloads would skip the link; two real machines never share memory."""
    from aeroperception.services.runtime.session import DEFAULT_CONFIG

    text = DEFAULT_CONFIG.read_text()
    assert "shared_memory: { enabled: true }" in text
    p = base / "ground-zenoh.json5"
    p.write_text(text.replace("shared_memory: { enabled: true }", "shared_memory: { enabled: false }"))
    return p


class Hosts:
    def __init__(self, lan, base: Path):
        self.lan, self.base = lan, base
        GROUND_ENV["AERO_ZENOH_CONFIG"] = str(_ground_config(base))
        self.vehicle, self.ground = lan["vehicle"], lan["ground"]
        self.delay_file = base / "relay_delay_ms"
        self.delay_file.write_text("0")
        # To the vehicle's own address: its router sees the ground's link on eth0, as on a real host.
        self.vehicle.relay(7448, f"{self.vehicle.addr}:7447", f"@{self.delay_file}")
        self.v_up = _up(self.vehicle, base / "vehicle", VEHICLE_SERVICES,
                        ["--listen", "tcp/0.0.0.0:7447", "--sensors", "none", "--thin-link", "eth0"])
        self.g_up = _up(self.ground, base / "ground", GROUND_SERVICES,
                        ["--listen", "tcp/127.0.0.1:7447", "--connect", f"tcp/{self.vehicle.addr}:7448"])
        self.g_obs = Observer(self.ground, GROUND_KEYS)
        self.v_obs = Observer(self.vehicle, ["sim/truth/state", "planner/status", "safety/status",
                                             "fmu/in/trajectory_setpoint", "fmu/out/vehicle_status",
                                             "sensors/camera/left/image", BULK])
        want = set(VEHICLE_SERVICES + GROUND_SERVICES)
        wait_until(lambda: want <= self.g_obs.alive() and want <= self.v_obs.alive(), 60,
                   f"liveliness of {sorted(want)} on both hosts", interval_s=0.5)
        wait_until(lambda: (self.g_obs.last("state/vehicle") or {}).get("connected"), 30,
                   "state/vehicle connected, seen on the ground")

    def pids(self) -> dict[str, int]:
        out = {}
        for side in ("vehicle", "ground"):
            p = self.base / side / "pids.json"
            out.update({f"{side}/{k}": v for k, v in json.loads(p.read_text()).items()} if p.exists() else {})
        return out

    def ground_aero(self, *args: str, timeout_s: float = 60.0):
        return self.ground.run(aero_argv() + list(args), timeout_s=timeout_s, env=_env())

    def describe(self) -> str:
        parts = []
        for side, names in (("vehicle", VEHICLE_SERVICES), ("ground", GROUND_SERVICES)):
            up = self.base / side / "aero-up.out"
            parts.append(f"--- {side} aero up:\n{up.read_text(errors='replace')[-2000:] if up.exists() else ''}")
            for n in names:
                p = self.base / side / f"{n}.log"
                parts.append(f"--- {side}/{n}.log:\n{p.read_text(errors='replace')[-1500:] if p.exists() else ''}")
        return "\n".join(parts)


def _env() -> dict[str, str]:
    """The ground's `aero` commands talk to the ground host's own router."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AERO_")}
    env.update(PYTHONUNBUFFERED="1", AERO_CONNECT="tcp/127.0.0.1:7447", **GROUND_ENV)
    return env


@pytest.fixture(scope="module")
def hosts(tmp_path_factory):
    from netns import Lan, netns_unavailable

    why = netns_unavailable()
    if why:
        pytest.skip(why)
    base = tmp_path_factory.mktemp("multihost")
    with Lan(["vehicle", "ground"]) as lan:
        h = Hosts(lan, base)
        yield h
        # Lan.__exit__ stops every process (aero up stops its services) and deletes the namespaces.
        for p in (h.g_up, h.v_up):
            p.send_signal(signal.SIGINT)
        for p in (h.g_up, h.v_up):
            try:
                p.wait(10)
            except Exception:  # noqa: BLE001 - Lan.close() kills what is left
                pass


def _mission_file(tmp_path: Path, spec: dict) -> Path:
    p = tmp_path / f"{spec['mission_id']}.json"
    p.write_text(json.dumps(spec))
    return p


def _land_and_wait(h: Hosts) -> None:
    h.ground_aero("mission", "command", "LAND", timeout_s=30)
    wait_until(lambda: (lambda s: s and not s.get("armed") and s["position_m"]["z"] < 0.3)(h.g_obs.last("sim/truth/state")),
               60, "landed and disarmed", interval_s=0.5)
    wait_until(lambda: (h.g_obs.last("mission/status") or {}).get("state") == "IDLE", 15, "mission IDLE")


def _rate(samples: list, window_s: float) -> float:
    return len(samples) / window_s if window_s > 0 else 0.0


@pytest.mark.slow
def test_mission_across_the_link(hosts, tmp_path):
    h = hosts
    t0 = time.monotonic()
    r = h.ground_aero("mission", "fly", str(_mission_file(tmp_path, LEAN)), "--quiet", "--timeout", "90", timeout_s=120)
    took = time.monotonic() - t0
    assert r.returncode == 0 and "2/2 done" in r.stdout, f"{r.stdout}\n{r.stderr}\n{h.describe()}"
    truth = [d["d"] for _t, d in h.v_obs.samples("sim/truth/state", since=t0)]
    assert max(s["position_m"]["x"] for s in truth) > 5.5, "the goto leg was not flown (truth)"
    print(f"multihost: lean mission flown from the ground host in {took:.1f} s")


@pytest.mark.slow
def test_link_cut_mid_flight(hosts, tmp_path):
    h = hosts
    pids_before = h.pids()
    fly = h.ground.follow(aero_argv() + ["mission", "fly", str(_mission_file(tmp_path, LONG_LEG)), "--timeout", "120"],
                          env=_env())
    try:
        # On the long leg (waypoint 1) and 4 m along it.
        def on_leg() -> bool:
            st = h.g_obs.last("mission/status") or {}
            return (st.get("state") == "EXECUTING" and st.get("active_waypoint") == 1
                    and (h.v_obs.last("sim/truth/state") or {}).get("position_m", {}).get("x", 0) > 4.0)

        try:
            wait_until(on_leg, 90, "EXECUTING on the 40 m leg, 4 m along", interval_s=0.1)
        except AssertionError as e:
            raise AssertionError(f"{e}\nfly: {[ln for _t, ln in fly.lines]}\nmission/status: "
                                 f"{h.g_obs.last('mission/status')}\ntruth: {h.v_obs.last('sim/truth/state')}") from None
        h.vehicle.link(False)
        t_cut = time.monotonic()
        time.sleep(CUT_S)
        h.vehicle.link(True)
        t_up = time.monotonic()

        # Vehicle side during the cut (its own observer): airborne, moving on/holding, setpoints flowing.
        during = [r["d"] for _t, r in h.v_obs.samples("sim/truth/state", since=t_cut, until=t_up)]
        setpoints = h.v_obs.samples("fmu/in/trajectory_setpoint", since=t_cut, until=t_up)
        vstatus = [r["d"] for _t, r in h.v_obs.samples("fmu/out/vehicle_status", since=t_cut, until=t_up)]
        safety = [r["d"] for _t, r in h.v_obs.samples("safety/status", since=t_cut, until=t_up)]
        assert min(s["position_m"]["z"] for s in during) > 2.0, "the vehicle sank during the cut"
        assert _rate(setpoints, t_up - t_cut) > 40, f"setpoint stream {_rate(setpoints, t_up - t_cut):.0f} Hz during the cut"
        modes = {s.get("nav_state_name") or s.get("flight_mode") or s.get("nav_state") for s in vstatus}
        x_cut, x_end = during[0]["position_m"]["x"], during[-1]["position_m"]["x"]
        # The planner's goal watchdog (2 s) stopped it: still at the end of the cut, not 10 m on.
        assert abs(during[-1]["velocity_mps"]["x"]) < 0.3, f"still flying at the end of the cut: {during[-1]}"
        assert x_end - x_cut < 2.0 * 2.0 + 2.0, f"flew {x_end - x_cut:.1f} m blind during the cut"
        gaps = [b - a for (a, _), (b, _) in zip(setpoints, setpoints[1:])]
        safety_msgs = sorted({(s.get("recommended_action"), tuple(s.get("errors") or ())) for s in safety})

        # Ground side after the link is back: every vehicle stream within RECOVERY_LIMIT_S.
        def first_after(key: str) -> float | None:
            s = h.g_obs.samples(key, since=t_up)
            return s[0][0] - t_up if s else None

        wait_until(lambda: all(first_after(k) is not None for k in VEHICLE_KEYS), 15,
                   "every vehicle key on the ground after the cut", interval_s=0.1)
        recovery = {k: round(first_after(k), 2) for k in VEHICLE_KEYS}
        gone = [t for t, r in h.g_obs.records(t_cut) if r.get("alive") and not r["put"]]

        # The mission on the ground saw the outage: HOLDING, and the vehicle stops.
        states = [r["d"]["state"] for _t, r in h.g_obs.samples("mission/status", since=t_cut)]
        wait_until(lambda: (h.g_obs.last("mission/status") or {}).get("state") == "HOLDING", 10,
                   f"mission HOLDING after the outage (states since the cut: {states[-5:]})")
        t_hold = time.monotonic()
        wait_until(lambda: (lambda s: s and abs(s["velocity_mps"]["x"]) < 0.3)(h.v_obs.last("sim/truth/state")),
                   10, "vehicle holding (|vx| < 0.3 m/s)")
        hold_s = time.monotonic() - t_hold
        x_hold = h.v_obs.last("sim/truth/state")["position_m"]["x"]
        time.sleep(2.0)
        x_later = h.v_obs.last("sim/truth/state")["position_m"]["x"]
        assert abs(x_later - x_hold) < 0.5, f"not holding: x {x_hold:.2f} -> {x_later:.2f} m (stale motion replayed?)"
        message = (h.g_obs.last("mission/status") or {}).get("message", "")

        print(f"multihost cut {CUT_S:.0f} s at x={x_cut:.1f} m: vehicle flew on to x={x_end:.1f} m during the cut "
              f"(planner held after goal_timeout_s), z min {min(s['position_m']['z'] for s in during):.2f} m; setpoints "
              f"{_rate(setpoints, t_up - t_cut):.0f} Hz, max gap {max(gaps) * 1000:.0f} ms; FC modes {modes}; "
              f"safety on the vehicle: {safety_msgs}")
        print(f"multihost: ground sees each vehicle key again after (s): {recovery}; "
              f"liveliness deletes seen on the ground during the cut: {len(gone)}")
        print(f"multihost: mission after the cut: HOLDING ({message!r}); vehicle stopped {hold_s:.1f} s after "
              f"that, x {x_hold:.1f} -> {x_later:.1f} m over 2 s")
        assert max(recovery.values()) <= RECOVERY_LIMIT_S, recovery
        assert h.pids() == pids_before, f"a process restarted: {pids_before} -> {h.pids()}"
        _land_and_wait(h)
    finally:
        if fly.proc.poll() is None:
            fly.proc.terminate()
            fly.proc.wait(10)
    assert h.pids() == pids_before


@pytest.mark.slow
@pytest.mark.extended   # 22 s; the link-cut flight across the namespaces runs by default
def test_impaired_link(hosts, tmp_path):
    """50 ms each way + 2 % loss each way: the lean mission flies from the ground."""
    h = hosts
    h.delay_file.write_text("50")
    h.vehicle.impair(loss_pct=2)
    try:
        time.sleep(1.0)
        t0 = time.monotonic()
        r = h.ground_aero("mission", "fly", str(_mission_file(tmp_path, LEAN)), "--quiet", "--timeout", "120",
                          timeout_s=150)
        t1 = time.monotonic()
        assert r.returncode == 0 and "2/2 done" in r.stdout, f"{r.stdout}\n{r.stderr}\n{h.describe()}"
        state = h.g_obs.samples("state/vehicle", since=t0, until=t1)
        ages = sorted(r["rx"] - r["st"] for _t, r in state if r.get("st"))
        print(f"multihost impaired A (50 ms each way + 2 % loss each way): lean mission from the ground "
              f"{t1 - t0:.1f} s; state/vehicle on the ground {_rate(state, t1 - t0):.0f} Hz, age median "
              f"{statistics.median(ages) * 1000:.0f} ms p95 {ages[int(0.95 * len(ages))] * 1000:.0f} ms")
    finally:
        h.vehicle.impair()
        h.delay_file.write_text("0")


def _p(values: list[float], q: float) -> float:
    return values[min(len(values) - 1, int(q * len(values)))] if values else float("nan")


def _saturate(h: Hosts, key: str, window_s: float) -> dict:
    """20 Hz raw 640x480 frames on `key` from the vehicle host for `window_s` (the ground follows
    the key): what the ground and the vehicle's own loop saw meanwhile."""
    src = h.vehicle.popen([sys.executable, "-c", IMAGES, "tcp/127.0.0.1:7447", key])
    try:
        wait_until(lambda: h.g_obs.samples(key, since=time.monotonic() - 2), 20, f"{key} on the ground")
        t0 = time.monotonic()
        q = h.ground_aero("param", "get", "planner", "kp", timeout_s=30)
        query = f"ok in {time.monotonic() - t0:.1f} s" if q.returncode == 0 else f"failed: {q.stderr.strip()[:80]}"
        time.sleep(max(0.0, window_s - (time.monotonic() - t0)))
        t1 = time.monotonic()
    finally:
        src.terminate()
        src.wait(10)
    win = t1 - t0
    state = h.g_obs.samples("state/vehicle", since=t0, until=t1)
    setp = h.v_obs.samples("fmu/in/trajectory_setpoint", since=t0, until=t1)
    stamps = [r["st"] for _t, r in setp if r.get("st")]
    local = h.v_obs.samples(key, since=t0, until=t1)     # the same frames to a subscriber on the vehicle
    return dict(local_hz=_rate(local, win), local_ages=sorted(r["rx"] - r["st"] for _t, r in local if r.get("st")),
        frames_hz=_rate(h.g_obs.samples(key, since=t0, until=t1), win), state_hz=_rate(state, win),
        ages=sorted(r["rx"] - r["st"] for _t, r in state if r.get("st")), setpoint_hz=_rate(setp, win),
        gap_s=max((b - a for (a, _), (b, _) in zip(setp, setp[1:])), default=float("inf")),
        stamp_gap_s=max((b - a for a, b in zip(stamps, stamps[1:])), default=float("inf")), query=query)


def _figures(name: str, key: str, m: dict) -> str:
    return (f"multihost impaired {name} (50 ms + 2 % loss each way, {RATE_KBIT / 1000:g} Mbit/s cap, 20 Hz raw "
            f"640x480 on {key}): ground gets {m['frames_hz']:.1f} frames/s, state/vehicle {m['state_hz']:.0f} Hz "
            f"age p50 {_p(m['ages'], 0.5) * 1000:.0f} ms p95 {_p(m['ages'], 0.95) * 1000:.0f} ms, `aero param get` "
            f"{m['query']}; vehicle setpoints {m['setpoint_hz']:.0f} Hz, max gap {m['gap_s'] * 1000:.0f} ms "
            f"(published {m['stamp_gap_s'] * 1000:.0f} ms); the frames on the vehicle {m['local_hz']:.1f} Hz, age "
            f"p50 {_p(m['local_ages'], 0.5) * 1000:.0f} ms p95 {_p(m['local_ages'], 0.95) * 1000:.0f} ms")


@pytest.mark.slow
def test_saturated_link_never_stalls_the_vehicle(hosts):
    """A 20 Mbit/s link (50 ms, 2 % loss) and 20 Hz raw 640x480 frames (147 Mbit/s) the ground
    subscribes to. B: the camera key, which the vehicle's `--thin-link eth0` sends at 1 Hz: the
    ground's state/vehicle stays fresh. C: a key no rule covers, which fills the link: the ground's
    view lags, but the vehicle's own loop never waits for the link. Before sim/truth/state (which
    the ground follows) dropped congestion control BLOCK, C stalled the vehicle's router: setpoint
    gaps up to 0.9 s (PX4 leaves OFFBOARD after 1.0 s). A subscriber on the vehicle gets the
    frames at their full rate and on time in both cases."""
    h = hosts
    h.delay_file.write_text("50")
    h.vehicle.impair(loss_pct=2, rate_kbit=RATE_KBIT)
    try:
        time.sleep(0.5)
        b = _saturate(h, "sensors/camera/left/image", 6.0)
        c = _saturate(h, BULK, 6.0)
    finally:
        h.vehicle.impair()
        h.delay_file.write_text("0")
    print(_figures("B, --thin-link", "sensors/camera/left/image", b))
    print(_figures("C, no rule", BULK, c))
    for name, m in (("B", b), ("C", c)):
        assert m["setpoint_hz"] > 45 and m["gap_s"] < 0.1, f"{name}: the vehicle's control loop stalled: {m['gap_s']:.2f} s"
        assert 0 < m["frames_hz"] < 15, f"{name}: frames should be sampled down by the slow link"
        # the vehicle's own subscribers (VIO, detector) get every frame on time: zenoh.json5 drops
        # a fragment that cannot be queued on the full link after 5 ms (zenoh's default 50 ms
        # made local delivery wait: p95 52 ms, 3 of 3 runs; 7 ms with 5 ms)
        assert m["local_hz"] > 18 and _p(m["local_ages"], 0.95) < 0.03, \
            f"{name}: the frames reach the vehicle's own subscribers late: {_figures(name, '', m)}"
    assert _p(b["ages"], 0.95) < 0.5 and b["state_hz"] > 25, f"B: state/vehicle on the ground stale: {_figures('B', '', b)}"
    assert b["query"].startswith("ok"), b["query"]
