"""safety: one verdict on whether the vehicle may keep flying (IF-2's SafetyStatus on safety/status).

It watches the required services' liveliness and health, the flight-controller link, battery,
geofence, ground-station link and perception health, and recommends an action from an explicit
rule table (rules.py). It never commands motion itself: mission acts on `recommended_action`,
gcs forwards the warnings; the only thing it can do to the vehicle is the operator's confirmed
emergency stop (safety/srv/emergency_stop -> fmu/srv/emergency_stop, FC flight termination).
geofence.py is the one geofence of the stack (mission checks waypoints with it).
"""
