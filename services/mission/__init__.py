"""mission: the mission manager of seed 000 §5.1 and the seed 002 actions.

The only service that commands the flight controller (through fmu/srv/*). Everyone else asks
it: operators and the GCS with mission/command, mission/srv/*, and the mission/action/* goals.
"""
