"""Scenario worlds for the simulator: YAML scenario model and the raycasting scene."""
