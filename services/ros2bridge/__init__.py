"""ros2bridge (optional): our keys as standard ROS 2 messages in rmw_zenoh's wire format, and one
ROS command topic (a PoseStamped goal) into the mission's goto action. ROS 2 nodes on rmw_zenoh
(`ros2 topic list/echo`) see the stack with no ROS installation here and no bridge of theirs.
It reads telemetry and sends goals through the mission like any operator: it never publishes
on fmu/in/** and never bypasses the mission's checks.
"""
