"""mission: the mission manager of requirement MIS-1 and the actions of IF-3.

The only service that commands the flight controller (through fmu/srv/*). Everyone else asks
it: operators and the GCS with mission/command, mission/srv/*, and the mission/action/* goals.
"""
