"""planner: the 50 Hz waypoint planner of requirement PLAN-1.

A P-controller on position error, output as a velocity setpoint with a speed cap; PX4's
velocity controller closes the inner loop. It publishes fmu/in/trajectory_setpoint every
cycle, even when holding (zero velocity at the hold point), so fmu never has to guess.
"""
