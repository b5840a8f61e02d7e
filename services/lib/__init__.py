"""The library layer: algorithms more than one service needs, imported, never run.

A service imports only this library, services.runtime (the process and transport), schemas (the
wire) and itself; services.mavlink (the NED/FRD boundary) only fmu, gcs and sim do. A service
never imports another service: what two of them share lives here, once (PX4's src/lib/ beside
src/modules/). Nothing here imports a service, opens a Zenoh session or reads a parameter by
itself; tests/unit/test_import_rules.py checks all of this.

- trajectory/: kinematic limits, the trajectory generators and the evaluation of Trajectory
  messages (planner flies them, mission checks a SetTrajectory goal with the same code);
- geofence: the fence and its parameters (safety measures against it, mission checks waypoints);
- pose_history: the vehicle's recent poses, interpolated or nearest at a sensor's stamp (lidar,
  objects);
- flight_state: on the ground / hovering, and the hover speed parameter (planner, mission);
- costmap: the costmap's cell values (lidar writes them, planner and mission judge by them);
- safety_names: the names of SafetyStatus's levels and actions (safety, mission);
- geo: WGS84 <-> local projection as PX4 does it (fmu, gcs, objects, sim).
Rotations live in services.runtime.rotations (every layer uses them, runtime included).
"""
