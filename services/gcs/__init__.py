"""gcs: the MAVLink endpoint that presents the stack to QGroundControl / MAVSDK / MAVProxy as one
PX4 autopilot.

main.py is the shell: the UDP link, a dispatch table {MAVLink message type: handler} and the
stack's topics. What a message asks of the stack goes through ops.py (the operations object:
every call answers one Outcome). The logic modules work without Zenoh:
  link, presence          UDP, parsing, signing; which ground stations are there (gcs/link)
  commands                COMMAND_LONG / COMMAND_INT -> one final COMMAND_ACK
  params, param_protocol  the stack's parameters as one MAVLink table; PARAM_* messages
  mission_items           mission items <-> the stack's Mission (about home.py's Home)
  mission_speed           DO_CHANGE_SPEED: the planner's speed, scoped to the mission
  mission_progress        MISSION_ITEM_REACHED / MISSION_CURRENT from the mission's progress
  mission_protocol        upload / download / clear state machine
  mission_sync            the protocol and progress kept in step with the mission service
  telemetry, messages     telemetry builders and intervals; MAVLink extension fields, STATUSTEXT
  safety_relay, objects_relay   safety/status and perception objects to ground stations
"""
