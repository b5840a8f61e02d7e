"""Test helpers shared by every test module (the fixtures in conftest.py are built on them).

The harness itself (aero up stacks, waits, captures, free ports, the MAVLink tap) lives in
aeroperception.tools.harness, shared with `aero chaos` and the benches; it is re-exported here so
test modules import everything from one place:

    from aerotest import free_port, zenoh_client, wait_until, wait_for_message, aero, Stack

Test-only helpers defined here:
    standalone_fc(fcu_port, log)           the simulated PX4 alone (MAVLink only), stopped on exit
    diagnostics_service(endpoint, log)     `aero run diagnostics` + a client session, for runtime tests
    validate_foxglove_export(path, n)      an `aero mcap export --foxglove` file checked against its schemas
    signal_other_thread(pid, sig)          a signal delivered to a non-main thread (tgkill)
    chaos_row_param(name, ci_rows, mark)   a fault row as a pytest param (xfail if pending, `mark` unless CI's)
    assert_chaos_row(st, row, mission)     run an `aero chaos` row; assert it safe by the truth and as expected
    forward_camera_info(y_m, ...)          a 640x480 pinhole looking forward from y_m on the body (VIO tests)
"""
from __future__ import annotations

import ctypes
import json
import os
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from aeroperception.tools.harness import (  # noqa: F401 - re-exported for the test modules
    Capture, MavlinkTap, SihTruth, SimStack, Stack, StackFactory, StackStartError, aero, aero_argv, clean_env, diag,
    free_port, free_udp_port, interrupt, is_service_process, latest, poll_until, pos, sample_stream, speed, stop_up,
    token_alive, wait_for_message, wait_until, zenoh_client,
)
from aeroperception.tools.harness.stack import STARTUP_TIMEOUT_S, STOP_TIMEOUT_S  # noqa: F401


def forward_camera_info(y_m: float, width: int = 640, height: int = 480, model: str = "plumb_bob"):
    """A pinhole camera (f = 320 px, centred) 0.1 m ahead of the body origin and y_m to its left,
    looking forward (FLU body): one of the VIO tests' stereo pair."""
    from aeroperception.schemas import CameraInfo, Pose, Quaternion, Vector3
    from aeroperception.services.runtime.rotations import quat_from_rotmat
    from aeroperception.services.sim.sensors.frames import R_FLU_OPTICAL_FORWARD

    q = Quaternion.from_array(quat_from_rotmat(R_FLU_OPTICAL_FORWARD))
    ci = CameraInfo.pinhole(width, height, 320.0, 320.0, (width - 1) / 2, (height - 1) / 2,
                            T_body_camera=Pose(position=Vector3(x=0.1, y=y_m, z=0.0), orientation=q))
    ci.distortion_model = model
    return ci


@contextmanager
def standalone_fc(fcu_port: int, log: Path):
    """The simulated PX4 run alone (MAVLink only, no Zenoh), as a PX4 SITL would be: it sends to
    127.0.0.1:`fcu_port`, where fmu listens (`--fcu-url udpin:127.0.0.1:PORT`). Stopped on exit."""
    from aeroperception.services.runtime.supervision import terminate

    with open(log, "wb") as err:
        fc = subprocess.Popen([sys.executable, "-m", "aeroperception.services.sim.vehicle", "--target",
                               f"127.0.0.1:{fcu_port}", "--bind", f"127.0.0.1:{free_port()}", "--status-every", "0"],
                              stdout=subprocess.DEVNULL, stderr=err)
    try:
        yield fc
    finally:
        terminate([fc], 5.0)


def validate_foxglove_export(path: Path, per_channel: int) -> dict[str, int]:
    """Every channel of an `aero mcap export --foxglove` file: JSON messages that validate against
    the file's own (Foxglove) JSON schemas, `per_channel` sampled each. Message counts per topic."""
    import jsonschema
    from mcap.reader import make_reader

    validators, counts = {}, {}
    with open(path, "rb") as f:
        for s, ch, m in make_reader(f).iter_messages():
            assert ch.message_encoding == "json", ch.topic
            v = validators.get(s.id) or validators.setdefault(s.id, jsonschema.Draft202012Validator(json.loads(s.data)))
            if counts.get(ch.topic, 0) < per_channel:
                v.validate(json.loads(m.data))
            counts[ch.topic] = counts.get(ch.topic, 0) + 1
    return counts


@contextmanager
def diagnostics_service(endpoint: str, log: Path, **popen: Any):
    """`aero run diagnostics` on `endpoint` (stderr into `log`; `popen` e.g. cwd, preexec_fn),
    yielded as (process, client session) once its liveliness token is seen; killed at exit if
    still running. The smallest real service, for tests of the runtime every service shares."""
    watcher = zenoh_client(endpoint)
    with open(log, "wb") as f:
        proc = subprocess.Popen(aero_argv() + ["run", "diagnostics"], stdout=subprocess.DEVNULL, stderr=f,
                                stdin=subprocess.DEVNULL, env=clean_env(endpoint), **popen)
    try:
        wait_until(lambda: token_alive(watcher, "diagnostics") or proc.poll() is not None, 20,
                   "the service's liveliness token")
        assert proc.poll() is None, log.read_text()
        yield proc, watcher
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        watcher.close()


def signal_other_thread(pid: int, sig: int) -> None:
    """Deliver `sig` to one of the process's threads other than the main one (tgkill), as the kernel
    may do with any process-directed signal: the Python handler still runs only on the main thread.
    A zenoh runtime thread (rx-/tx-/net-/app-) if there is one, else the oldest: long-lived either way,
    so the signal is not lost with a thread that exits."""
    tids = sorted(int(t) for t in os.listdir(f"/proc/{pid}/task") if int(t) != pid)
    assert tids, "the process has no other threads"
    named = [t for t in tids if Path(f"/proc/{pid}/task/{t}/comm").read_text().startswith(("rx-", "tx-", "net-", "app-"))]
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.tgkill(pid, (named or tids)[0], int(sig)) != 0:
        raise OSError(ctypes.get_errno(), "tgkill failed")


def chaos_row_param(name: str, ci_rows: tuple[str, ...], mark: Any):
    """An `aero chaos` row as a pytest param, `mark`ed (e.g. pytest.mark.extended) unless CI flies it (`ci_rows`)."""
    import pytest

    return pytest.param(name, marks=[] if name in ci_rows else [mark], id=name)


def assert_chaos_row(st: Any, row: Any, mission_json: str) -> None:
    """Fly `row` on `st` (a SimStack or Px4Stack): the vehicle safe by the truth, the row's expected outcome met."""
    from aeroperception.tools.cli.chaos import run_row

    res = run_row(st, row, mission_json)
    print(f"{row.name} ({st.profile}): {res.verdict} in {res.duration_s:.0f} s; observed: {res.observed}; "
          f"safe: {res.safe_why}; detect/react {res.detect_s}")
    assert res.safe, f"{row.name}: vehicle not safe by the truth: {res.safe_why} (observed: {res.observed})"
    assert res.passed, f"{row.name}: expected {row.expected!r}; observed {res.observed!r}"


def euroc_camchain(mav: Path, path: Path, stereo: bool = True) -> Any:
    """A Kalibr camchain of EuRoC's VI-Sensor written from its real sensor.yaml files (intrinsics,
    radtan distortion, T_cam_imu = inverse of T_BS: the IMU is the body) to `path`; returns cam0's
    T_BS (4x4), where the camera driver must place the left camera."""
    import numpy as np
    import yaml

    chain, t_bs0 = {}, None
    for cam in ("cam0", "cam1")[: 2 if stereo else 1]:
        text = (mav / cam / "sensor.yaml").read_text()
        y = yaml.safe_load(text.split("\n", 1)[1] if text.startswith("%YAML") else text)   # OpenCV's header
        t_bs = np.array(y["T_BS"]["data"], float).reshape(4, 4)
        t_bs0 = t_bs if t_bs0 is None else t_bs0
        chain[cam] = dict(camera_model="pinhole", intrinsics=y["intrinsics"], distortion_model="radtan",
                          distortion_coeffs=y["distortion_coefficients"], resolution=y["resolution"],
                          T_cam_imu=np.linalg.inv(t_bs).tolist())
    path.write_text(yaml.safe_dump(chain))
    return t_bs0
