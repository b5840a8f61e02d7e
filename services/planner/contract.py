"""Contract of the planner: keys in/out (ENU) and parameters. The service is wired from it
(Node.bind: each input to on_<key>, e.g. on_state_vehicle) and configured from PARAMS (config.py).

The planner owns all three swappable parts (trajectory generator, controller, estimator) because
it is the one that turns the goal into setpoints: the generator shapes the reference, the
controller chooses what of it the flight controller gets, the estimator is what the planner
measures progress and error against. One owner keeps the rule for a safe switch (plugins.py) and
the value of what runs in one place; the mission only names a generator for its own waypoints (a
mission file's trajectory section, carried in the Trajectory's generator_name).
"""
from aeroperception.schemas import (
    MissionGoal, OccupancyGrid, Odometry, SelectPluginReply, SelectPluginRequest, Trajectory, TrajectorySetpoint,
    TrajectoryStatus, VehicleState, WaypointReached,
)
from aeroperception.services.lib.flight_state import HOVER_SPEED_PARAM
from aeroperception.services.lib.trajectory.generators import GENERATORS
from aeroperception.services.runtime import EXPRESS, Param, Queries, Query, Topic, Topics

from .controllers import CONTROLLERS
from .estimators import ESTIMATORS

NAME = "planner"
INPUTS = Topics(
    Topic("state/vehicle", VehicleState),
    # The goal to fly to (with its own speed caps). header.frame_id MissionGoal.HOLD_FRAME: stop and hold where you are.
    Topic("mission/active_goal", MissionGoal, strict=True),
    # The lidar service's rolling costmap: obstacle-aware velocity (planner/avoidance.py).
    Topic("perception/costmap", OccupancyGrid),
    # The whole way to fly (smooth waypoints or a typed trajectory), flown while the goal is on it (planner/tracking.py).
    Topic("mission/active_trajectory", Trajectory, note="on change + 2 Hz; empty = none", strict=True),
    Topic("state/visual_odometry", Odometry, note="the vio estimator's input (freshness checked before a switch to it)"),
)
SERVICES = Queries(
    Query("planner/srv/select_plugin", SelectPluginRequest, SelectPluginReply,
          note="SetTrajectoryGenerator / SetController / SetEstimator (role); refused moving or for an unknown name"),
)
STATUS_RATE_HZ = 10.0
OUTPUTS = Topics(
    Topic("fmu/in/trajectory_setpoint", TrajectorySetpoint, 50.0, note="always (rate_hz)", qos=EXPRESS),
    Topic("planner/status", TrajectoryStatus, STATUS_RATE_HZ, note="progress, times, setpoint, errors"),
    Topic("planner/waypoint_reached", WaypointReached, note="event; index = n-th goal received"),
)
PARAMS = [
    Param("max_velocity_mps", 2.0, "m/s", 0.1, 15.0, description="speed cap of the velocity command"),
    Param("kp", 0.8, "1/s", 0.05, 5.0, description="proportional gain on position error"),
    Param("acceptance_radius_m", 0.5, "m", 0.05, 10.0, description="goal counts as reached inside this"),
    Param("rate_hz", 50.0, "Hz", 10.0, 200.0, description="setpoint rate"),
    Param("state_timeout_s", 0.5, "s", 0.05, 5.0, description="older vehicle state -> hold, status ERROR"),
    Param("goal_timeout_s", 2.0, "s", 0.0, 30.0,
          description="no mission/active_goal (re-sent at 2 Hz) this long while tracking -> hold where it is (0: off)"),
    Param("obstacle_avoidance", True, description="steer around perception/costmap obstacles (off: straight lines)"),
    Param("avoid_clearance_m", 1.5, "m", 0.3, 10.0, description="keep this far from obstacles (plus tracking error)"),
    Param("avoid_goal_clearance_m", 1.0, "m", 0.1, 10.0,
          description="a goal nearer than this to an obstacle is unreachable; nearer than avoid_clearance_m "
                      "it is approached no closer than the goal itself"),
    Param("avoid_lookahead_m", 1.0, "m", 0.3, 10.0, description="farthest visible point along the planned way"),
    Param("avoid_slow_distance_m", 3.0, "m", 0.5, 20.0, description="slow down when the clearance zone ahead is nearer"),
    Param("avoid_stop_distance_m", 0.2, "m", 0.0, 5.0, description="zero speed this close to the clearance zone ahead"),
    # trajectories (mission/active_trajectory): limits with PX4's names; max_velocity_mps is MPC_XY_VEL_MAX's part.
    # A change applies to the next trajectory made (the one being flown keeps its timing).
    Param("acc_hor_mps2", 3.0, "m/s^2", 0.2, 20.0, description="MPC_ACC_HOR: horizontal acceleration limit"),
    Param("acc_up_mps2", 4.0, "m/s^2", 0.2, 20.0, description="MPC_ACC_UP_MAX: upward acceleration limit"),
    Param("acc_down_mps2", 3.0, "m/s^2", 0.2, 20.0, description="MPC_ACC_DOWN_MAX: downward acceleration limit"),
    Param("jerk_mps3", 4.0, "m/s^3", 0.2, 100.0, description="MPC_JERK_AUTO: jerk limit"),
    Param("z_vel_max_up_mps", 3.0, "m/s", 0.1, 15.0, description="MPC_Z_VEL_MAX_UP: climb rate limit"),
    Param("z_vel_max_dn_mps", 1.5, "m/s", 0.1, 15.0, description="MPC_Z_VEL_MAX_DN: descent rate limit"),
    Param("yaw_rate_max_dps", 45.0, "deg/s", 1.0, 360.0, description="MPC_YAWRAUTO_MAX: heading rate limit"),
    # the acceleration feed-forward a trajectory streams (follow.py FeedForward): what the flight
    # controller must command now, for its lag and the drag it does not model (0 = the reference's own)
    Param("ff_lead_s", 0.0, "s", 0.0, 1.0,
          description="the flight controller's lag from an acceleration setpoint to the vehicle's acceleration: "
                      "the acceleration is taken this far ahead on the trajectory (PX4's SIH quad: 0.25)"),
    Param("drag_per_s", 0.0, "1/s", 0.0, 5.0,
          description="the vehicle's linear drag, acceleration lost per m/s: drag_per_s x velocity is added to the "
                      "acceleration (PX4's SIH quad: SIH_KDV / SIH_MASS = 1; the built-in sim: SIM_DRAG)"),
    Param("fc_xy_vel_d", 0.0, "", 0.0, 2.0,
          description="the flight controller's velocity-loop D gain on the vehicle's measured horizontal acceleration "
                      "(PX4: MPC_XY_VEL_D_ACC, 0.2): the reference's acceleration x this is added to the feed-forward, "
                      "so the FC does not subtract it from the turn (0 = off)"),
    Param("fc_xy_gain_per_s", 0.0, "1/s", 0.0, 10.0,
          description="the flight controller's horizontal position gain (PX4: MPC_XY_P, 0.95): a trajectory's clock "
                      "is held back so that feed-forward + this x the position error stays within max_velocity_mps "
                      "(+5 %): PX4 caps its catch-up only at its own MPC_XY_VEL_MAX (0 = off)"),
    Param("fc_velocity_error_mps", 0.0, "m/s", 0.0, 1.0,
          description="how far the flight controller's velocity estimate may be off the vehicle's true velocity (it "
                      "flies its estimate: at the cap, the truth is this much faster): a generated trajectory is "
                      "timed, and the governor caps, this far below max_velocity_mps and the climb/descent caps "
                      "(never below half of each); typed trajectories and goal-by-goal flight are not (0 = off)"),
    Param("fc_jerk_error_mps3", 0.0, "m/s^3", 0.0, 50.0,
          description="how much jerk the flight controller's tracking adds to the reference's (its loops correcting "
                      "its estimate's error, its height hold): a generated trajectory is planned this far below "
                      "jerk_mps3 (never below half of it), so that the vehicle's jerk stays within it; typed "
                      "trajectories and goal-by-goal flight are not (0 = off)"),
    Param("trajectory_lag_m", 1.5, "m", 0.2, 20.0,
          description="the reference slows while the vehicle is more than half this behind it, stops at this"),
    # swappable parts (plugins.py): switched live only on the ground or hovering
    Param("trajectory_generator", "waypoint", choices=tuple(GENERATORS),
          description="how a mission's waypoints are flown unless it names its own: waypoint = goal by goal "
                      "(P-controller), smooth = one jerk-limited trajectory through them"),
    Param("controller", "feedforward", choices=tuple(CONTROLLERS),
          description="feedforward = position + velocity + acceleration to the FC; velocity = velocity only, "
                      "the planner closes the position loop (kp)"),
    Param("estimator", "fc", choices=tuple(ESTIMATORS),
          description="fc = the FC's estimate (state/vehicle); vio = VIO's odometry directly (state/visual_odometry)"),
    Param("state_dir", "", start_only=True,
          description="where the selected parts persist (plugins.PARTS_FILE); '' = $AERO_STATE_DIR or ~/.aero/state, /<vehicle>/"),
    HOVER_SPEED_PARAM,
    Param("costmap_timeout_s", 0.5, "s", 0.1, 5.0, description="an older costmap -> hold until fresh (stale_costmap); none ever -> straight lines"),
]
