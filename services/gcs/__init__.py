"""gcs: the MAVLink endpoint that presents the stack to QGroundControl / MAVSDK / MAVProxy as one
PX4 autopilot (seed 001). Logic modules (link, missions, params, commands, telemetry) work without
Zenoh; main.py wires them to the stack."""
