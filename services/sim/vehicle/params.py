"""Every parameter of the simulated vehicle, declared once (like a PX4 module.yaml).

Names follow PX4 where PX4 has the parameter (same meaning, same default unless noted) so
someone who knows PX4 can tune the sim without a dictionary; SIM_* are the simulator's own.
Names are at most 16 characters: they are also served over the MAVLink parameter protocol.
"""
from __future__ import annotations

from typing import Any, Mapping

from aeroperception.services.runtime.params import Param, ParamSet

PARAMS: tuple[Param, ...] = (
    # --- airframe and environment (SIM_*) ---
    Param("SIM_MASS", 1.5, "kg", 0.1, 50.0, description="vehicle mass"),
    Param("SIM_TWR", 2.0, "", 1.1, 6.0, description="max thrust / weight; hover thrust = 1/SIM_TWR"),
    Param("SIM_DRAG", 0.25, "1/s", 0.0, 5.0, description="linear drag: accel = -SIM_DRAG * airspeed"),
    Param("SIM_ATT_TAU", 0.1, "s", 0.01, 1.0, description="first-order attitude response time constant"),
    Param("SIM_THR_TAU", 0.03, "s", 0.001, 0.5, description="motor thrust response time constant"),
    Param("SIM_WIND_N", 0.0, "m/s", -30.0, 30.0, description="constant wind towards North"),
    Param("SIM_WIND_E", 0.0, "m/s", -30.0, 30.0, description="constant wind towards East"),
    Param("SIM_WIND_GUST", 0.0, "m/s", 0.0, 10.0, description="gust std-dev (Ornstein-Uhlenbeck per axis)"),
    Param("SIM_GUST_TAU", 2.0, "s", 0.1, 60.0, description="gust correlation time"),
    Param("SIM_POS_NOISE", 0.01, "m", 0.0, 5.0, description="std-dev of the reported local position"),
    Param("SIM_VEL_NOISE", 0.02, "m/s", 0.0, 5.0, description="std-dev of the reported velocity"),
    Param("SIM_ACC_NOISE", 0.05, "m/s^2", 0.0, 5.0, description="accelerometer white noise std-dev"),
    Param("SIM_GYRO_NOISE", 0.003, "rad/s", 0.0, 1.0, description="gyro white noise std-dev"),
    Param("SIM_BARO_NOISE", 0.05, "m", 0.0, 5.0, description="barometric altitude noise std-dev"),
    Param("SIM_POS_VALID", True, description="the estimator has a position (false: arming is refused)"),
    # --- GPS-denied estimation (estimator.py; EKF2_* as PX4's EKF2 with EKF2_EV_CTRL) ---
    Param("SIM_GPS_DENIED", False,
          description="no GPS-like position: the FC estimates position only from vision ODOMETRY fused with its IMU"),
    Param("EKF2_EV_NOISE_MD", 0, "", 0, 1,
          description="vision noise: 0 the sample's covariance floored at EKF2_EVP/EVV_NOISE (PX4's default), "
                      "1 EKF2_EVP/EVV_NOISE only (for a VIO whose covariance includes its accumulated drift)"),
    Param("EKF2_EVP_NOISE", 0.1, "m", 0.01, 10.0, description="vision position noise (floor with EKF2_EV_NOISE_MD 0)"),
    Param("EKF2_EVV_NOISE", 0.1, "m/s", 0.01, 10.0, description="vision velocity noise (floor with EKF2_EV_NOISE_MD 0)"),
    Param("EKF2_NOAID_TOUT", 5.0, "s", 0.5, 10.0,
          description="no vision fused this long -> no valid position (PX4's dead-reckoning limit)"),
    Param("SIM_EV_REALIGN_T", 1.0, "s", 0.1, 60.0,
          description="vision back after a gap this long -> re-align its odom frame (a re-initialised VIO)"),
    Param("SIM_CAM_BLACKOUT", 0.0, "s", 0.0, 600.0,
          description="fault: cameras see black for this long from when it is set (0: none)"),
    Param("SIM_HOME_LAT", 47.397742, "deg", -90.0, 90.0, description="home / local origin latitude"),
    Param("SIM_HOME_LON", 8.545594, "deg", -180.0, 180.0, description="home / local origin longitude"),
    Param("SIM_HOME_ALT", 488.0, "m", -500.0, 9000.0, description="home altitude AMSL (ground level)"),
    # --- battery ---
    Param("SIM_BAT_CAP", 5000.0, "mAh", 100.0, 100000.0, description="battery capacity"),
    Param("SIM_BAT_CELLS", 4, "", 1, 14, description="series cells"),
    Param("SIM_BAT_MAX_A", 40.0, "A", 1.0, 500.0, description="current at full thrust (I ~ thrust^1.5)"),
    Param("SIM_BAT_IDLE_A", 0.5, "A", 0.0, 20.0, description="current when armed at zero thrust"),
    Param("SIM_BAT_R", 0.02, "ohm", 0.0, 1.0, description="pack internal resistance (voltage sag)"),
    Param("SIM_BAT_DRAIN", 1.0, "", 0.0, 1000.0, description="drain speed-up factor (tests of low battery)"),
    Param("BAT_V_EMPTY", 3.5, "V", 2.5, 4.0, description="cell voltage when empty"),
    Param("BAT_V_CHARGED", 4.05, "V", 3.5, 4.4, description="cell voltage when full"),
    Param("BAT_LOW_THR", 0.15, "", 0.0, 0.5, description="low battery warning level"),
    Param("BAT_CRIT_THR", 0.07, "", 0.0, 0.5, description="critical battery level"),
    Param("BAT_EMERGEN_THR", 0.05, "", 0.0, 0.5, description="emergency battery level"),
    # --- commander (arming, failsafes) ---
    Param("COM_OF_LOSS_T", 1.0, "s", 0.0, 60.0, description="offboard setpoints silent this long -> failsafe"),
    Param("COM_OBL_ACT", 2, "", choices=(0, 1, 2),
          description="offboard-loss failsafe: 0 LAND, 1 HOLD (then LAND after COM_OBL_HOLD_T), 2 RTL. "
                      "2 is what PX4 SITL does by default (COM_OBL_RC_ACT with no RC falls back to "
                      "NAV_RCL_ACT = Return)"),
    Param("COM_OBL_HOLD_T", 5.0, "s", -1.0, 600.0,
          description="with COM_OBL_ACT 1: HOLD this long, then LAND (-1: hold forever)"),
    Param("SIM_OF_RESUME", True,
          description="setpoints back during the offboard-loss failsafe -> OFFBOARD again (PX4 SITL does: "
                      "the failsafe clears with its condition)"),
    Param("SIM_REBOOT_T", 2.0, "s", 0.0, 30.0,
          description="PREFLIGHT_REBOOT: the autopilot is silent this long, then back at default stream rates"),
    Param("COM_OF_MIN_HZ", 2.0, "Hz", 0.1, 100.0, description="setpoint stream must be faster than this"),
    Param("COM_OF_WARM_T", 1.0, "s", 0.0, 10.0, description="...for this long before OFFBOARD is accepted"),
    Param("COM_DISARM_LAND", 2.0, "s", -1.0, 20.0, description="auto-disarm after landing (-1: never)"),
    Param("COM_DISARM_PRFLT", 10.0, "s", -1.0, 60.0, description="auto-disarm if no takeoff after arming (-1: never)"),
    Param("COM_LOW_BAT_ACT", 0, "", choices=(0, 3),
          description="0: warn only; 3: RTL at critical, LAND at emergency battery"),
    Param("LNDMC_TRIG_TIME", 1.0, "s", 0.1, 10.0, description="on the ground this long -> landed"),
    # --- auto modes ---
    Param("MIS_TAKEOFF_ALT", 2.5, "m", 0.0, 100.0, description="default takeoff altitude above home"),
    Param("MPC_TKO_SPEED", 1.5, "m/s", 0.5, 5.0, description="takeoff climb rate"),
    Param("MPC_LAND_SPEED", 0.7, "m/s", 0.3, 3.0, description="landing descent rate below MPC_LAND_ALT2"),
    Param("MPC_LAND_ALT1", 10.0, "m", 0.0, 122.0, description="above this, land at MPC_Z_VEL_MAX_DN"),
    Param("MPC_LAND_ALT2", 5.0, "m", 0.0, 122.0, description="below this, land at MPC_LAND_SPEED"),
    Param("MPC_XY_CRUISE", 5.0, "m/s", 1.0, 20.0, description="horizontal speed in auto modes (RTL)"),
    Param("RTL_RETURN_ALT", 60.0, "m", 0.0, 1000.0, description="RTL climbs to this height above home"),
    Param("NAV_ACC_RAD", 1.0, "m", 0.05, 200.0, description="acceptance radius for auto-mode targets"),
    # --- position control (mc_pos_control) ---
    Param("MPC_XY_P", 0.95, "1/s", 0.0, 2.0, description="horizontal position gain"),
    Param("MPC_Z_P", 1.0, "1/s", 0.1, 1.5, description="vertical position gain"),
    Param("MPC_XY_VEL_P_ACC", 1.8, "1/s", 1.2, 5.0, description="horizontal velocity P"),
    Param("MPC_XY_VEL_I_ACC", 0.4, "1/s^2", 0.0, 60.0, description="horizontal velocity I"),
    Param("MPC_XY_VEL_D_ACC", 0.2, "", 0.1, 2.0, description="horizontal velocity D"),
    Param("MPC_Z_VEL_P_ACC", 4.0, "1/s", 2.0, 15.0, description="vertical velocity P"),
    Param("MPC_Z_VEL_I_ACC", 2.0, "1/s^2", 0.2, 3.0, description="vertical velocity I"),
    Param("MPC_Z_VEL_D_ACC", 0.0, "", 0.0, 2.0, description="vertical velocity D"),
    Param("MPC_XY_VEL_MAX", 12.0, "m/s", 0.0, 20.0, description="horizontal speed limit"),
    Param("MPC_Z_VEL_MAX_UP", 3.0, "m/s", 0.5, 8.0, description="climb rate limit"),
    Param("MPC_Z_VEL_MAX_DN", 1.5, "m/s", 0.5, 4.0, description="descent rate limit"),
    Param("MPC_TILTMAX_AIR", 35.0, "deg", 20.0, 89.0, description="tilt limit (PX4 default 45)"),
    Param("MPC_THR_MIN", 0.12, "", 0.05, 0.5, description="minimum collective thrust in flight (of max)"),
    Param("MPC_ACC_HOR", 3.0, "m/s^2", 2.0, 15.0, description="braking deceleration when entering HOLD"),
    Param("MC_ROLLRATE_MAX", 220.0, "deg/s", 0.0, 1800.0, description="roll/pitch rate limit"),
    Param("MC_YAWRATE_MAX", 60.0, "deg/s", 0.0, 1800.0, description="yaw rate limit (FC-6: 60)"),
)


def make_params(overrides: Mapping[str, Any] | None = None) -> ParamSet:
    """A fresh, validated parameter set; unknown names or bad values raise ParamError."""
    ps = ParamSet.from_declarations(PARAMS)
    if overrides:
        ps.update(dict(overrides))
    return ps
