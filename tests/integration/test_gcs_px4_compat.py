"""gcs against the sim stack, as PX4 ground-station software expects an autopilot to behave:
PX4 parameter names read and set through MAVSDK and MAVProxy, mode
changes answered with one final COMMAND_ACK (MAVSDK manual control), ignored setpoints counted,
and mission progress to "finished" with MAVSDK's Mission plugin."""
from __future__ import annotations

import asyncio
import json
import time

import pytest

from aeroperception.schemas import DiagnosticStatus, MissionStatus, VehicleState
from aerotest import free_udp_port, wait_for_message, wait_until
from test_gcs import (
    HOME, Gcs, MavProxy, mavsdk_autopilot, start_stack, wait_until_value,
)
from pymavlink.dialects.v20 import common as M


async def _retry(fn, timeout_s: float, what: str):
    """fn() until it stops raising (the parameter table fills as services answer @params)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return await asyncio.wait_for(fn(), 5)
        except Exception as e:  # noqa: BLE001 - MAVSDK's ParamError / timeouts while the table fills
            if time.monotonic() > deadline:
                raise AssertionError(f"{what}: {e}") from e
            await asyncio.sleep(0.5)


def test_px4_parameter_names_mode_change_and_ignored_setpoints(stack, tmp_path):
    pytest.importorskip("mavsdk.asyncio")
    from mavsdk.asyncio.plugins.manual_control.manual_control import ManualControlAsync
    from mavsdk.asyncio.plugins.param.param import ParamAsync

    port, sdk_port = free_udp_port(), free_udp_port()
    st = start_stack(stack, port, sdk_port)
    get = lambda svc, name: st.aero("param", "get", svc, name).stdout.strip()   # noqa: E731
    timing: dict[str, float] = {}

    async def session():
        async with mavsdk_autopilot(sdk_port) as system:
            param = ParamAsync(system)
            # PX4 names, the services' live values
            assert await _retry(lambda: param.get_param_float("MIS_TAKEOFF_ALT"), 20, "MIS_TAKEOFF_ALT") == 3.0
            assert await _retry(lambda: param.get_param_float("RTL_RETURN_ALT"), 20, "RTL_RETURN_ALT") == 60.0
            assert await param.get_param_float("MPC_XY_VEL_MAX") == pytest.approx(2.0)
            assert await param.get_param_float("NAV_ACC_RAD") == pytest.approx(0.5)
            assert await param.get_param_int("NAV_DLL_ACT") == 1           # the mission holds on GCS loss
            assert await param.get_param_int("COM_RC_IN_MODE") == 4
            await asyncio.wait_for(param.set_param_float("MIS_TAKEOFF_ALT", 4.5), 10)
            await asyncio.wait_for(param.set_param_float("MPC_XY_VEL_MAX", 3.0), 10)
            await asyncio.wait_for(param.set_param_float("RTL_RETURN_ALT", 30.0), 10)
            with pytest.raises(Exception):                                  # read-only: refused, unchanged
                await asyncio.wait_for(param.set_param_int("NAV_DLL_ACT", 2), 10)
            with pytest.raises(Exception):                                  # unknown: PX4's silence
                await asyncio.wait_for(param.get_param_float("NOT_A_PX4_PARAM"), 10)

            # a mode change answered once, finally, within MAVSDK's timeout
            manual = ManualControlAsync(system)
            await manual.set_manual_control_input(0.0, 0.0, 0.5, 0.0)
            t0 = time.monotonic()
            await asyncio.wait_for(manual.start_position_control(), 10)
            timing["posctl_s"] = time.monotonic() - t0

    asyncio.run(asyncio.wait_for(session(), 120))
    assert get("mission", "takeoff_altitude_m") == "4.5"
    assert get("planner", "max_velocity_mps") == "3.0"
    assert get("sim", "RTL_RETURN_ALT") == "30.0"
    wait_until(lambda: (v := st.latest("state/vehicle", VehicleState, 1.0)) is not None and v.flight_mode == "POSCTL",
               5, "the vehicle in POSCTL")
    print(f"start_position_control answered after {timing['posctl_s']:.2f} s")

    # MAVProxy shows a PX4 name (it talks first: udpout to gcs)
    mp = MavProxy(f"udpout:127.0.0.1:{port}", tmp_path / "mavproxy")
    try:
        mp.expect(r"Detected vehicle 1:1", timeout_s=30)
        mp.expect(r"Received \d+ parameters", timeout_s=15)
        mark = mp.send("param show MIS_TAKEOFF_ALT")
        assert float(mp.expect(r"MIS_TAKEOFF_ALT\s+(-?[\d.]+)\s*$", after=mark).group(1)) == pytest.approx(4.5)
        mark = mp.send("param set GF_ACTION 2")        # no safety service here: not a parameter
        mp.expect(r"unknown param: GF_ACTION|Unable to find parameter|unknown parameter", timeout_s=10, after=mark)
    finally:
        mp.stop()

    # a ground station's position setpoint is ignored, and counted
    g = Gcs(port)
    try:
        g.heartbeat()
        g.conn.mav.set_position_target_local_ned_send(0, 1, 1, M.MAV_FRAME_LOCAL_NED, 0b110111111000,
                                                      5.0, 0.0, -3.0, 0, 0, 0, 0, 0, 0, 0, 0)
        diag = wait_for_message(st.session, "diagnostics/gcs", DiagnosticStatus,
                                lambda d: int(d.values.get("ignored[SET_POSITION_TARGET_LOCAL_NED]", 0)) >= 1,
                                timeout_s=5)
        assert int(diag.values["ignored"]) >= 1
        g.conn.mav.command_long_send(1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                                     0, 0, 0, 0, 0, 0)
        av = g.recv("AUTOPILOT_VERSION")
        assert not av.capabilities & M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    finally:
        g.close()
    assert st.alive("gcs")


@pytest.mark.slow
def test_mavsdk_mission_progress_reaches_finished(stack):
    """Issue 9 #2: MAVSDK's Mission plugin uploads 3 waypoints, starts the mission on the ground;
    MISSION_ITEM_REACHED for every item including the last, progress 3/3, is_mission_finished()
    true, and MISSION_CURRENT ends COMPLETE with seq == total."""
    pytest.importorskip("mavsdk.asyncio")
    from mavsdk.asyncio.plugins.action.action import ActionAsync
    from mavsdk.asyncio.plugins.mavlink_direct.mavlink_direct import MavlinkDirectAsync
    from mavsdk.asyncio.plugins.mission.mission import MissionAsync
    from mavsdk.plugins.mission import MissionItem, MissionPlan

    port, sdk_port = free_udp_port(), free_udp_port()
    st = start_stack(stack, port, sdk_port)
    wait_until(lambda: (m := st.latest("state/vehicle", VehicleState, 1.0)) is not None and m.connected, 15,
               "state/vehicle connected")
    # the simulated FC accepts OFFBOARD only after > 1 s of fmu's setpoint stream (PX4's rule)
    wait_until(lambda: (d := st.latest("diagnostics/fmu", DiagnosticStatus, 1.0)) is not None
               and d.values.get("planner") == "streaming", 15, "fmu streaming the planner's setpoints")
    time.sleep(2.0)
    pts = [HOME.projection.reproject(n, e) for n, e in ((3.0, 0.0), (3.0, 3.0), (0.0, 3.0))]
    plan = MissionPlan([MissionItem(latitude_deg=lat, longitude_deg=lon, relative_altitude_m=3.0, speed_m_s=None,
                                    is_fly_through=False, acceptance_radius_m=0.5) for lat, lon in pts])
    reached: list[int] = []
    progress: list[tuple[int, int]] = []
    current: list[dict] = []
    result: dict[str, object] = {}

    async def session():
        async with mavsdk_autopilot(sdk_port) as system:
            mission, action, direct = MissionAsync(system), ActionAsync(system), MavlinkDirectAsync(system)

            async def collect(name, sink, conv):
                async for m in direct.subscribe_message(name):
                    sink.append(conv(json.loads(m.fields_json)))

            async def collect_progress():
                async for p in mission.subscribe_mission_progress():
                    progress.append((p.current, p.total))

            tasks = [asyncio.create_task(collect("MISSION_ITEM_REACHED", reached, lambda f: int(f["seq"]))),
                     asyncio.create_task(collect("MISSION_CURRENT", current, lambda f: f)),
                     asyncio.create_task(collect_progress())]
            try:
                await asyncio.wait_for(mission.upload_mission(plan), 30)
                await asyncio.wait_for(action.arm(), 15)
                await asyncio.wait_for(mission.start_mission(), 15)
                deadline = time.monotonic() + 70
                while not await mission.is_mission_finished():
                    assert time.monotonic() < deadline, f"not finished; reached {reached}, progress {progress[-3:]}"
                    await asyncio.sleep(0.3)
                result["finished"] = True
                await asyncio.sleep(1.5)   # MISSION_CURRENT after completion
                p = await mission.mission_progress()
                result["progress"] = (p.current, p.total)
            finally:
                for t in tasks:
                    t.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)

    asyncio.run(asyncio.wait_for(session(), 150))
    print(f"reached {reached}; progress {progress}; last MISSION_CURRENT {current[-1] if current else None}")
    assert result["finished"] is True
    assert reached == [0, 1, 2]
    assert result["progress"] == (3, 3) and progress[-1] == (3, 3)
    last = current[-1]
    assert (last["seq"], last["total"], last["mission_state"]) == (3, 3, M.MISSION_STATE_COMPLETE)
    assert any(c["mission_state"] == M.MISSION_STATE_ACTIVE for c in current)
    wait_until(lambda: (m := st.latest("mission/status", MissionStatus, 1.0)) is not None and m.state == "IDLE", 40,
               "landed (mission IDLE)")
    assert wait_until_value(lambda: st.aero("param", "get", "planner", "max_velocity_mps").stdout.strip(),
                            "2.0", timeout_s=3) == "2.0"
