"""Real recordings played into a live stack at their own timing (`aero play`): a dataset's
sensors as the drivers on a vehicle would publish them, so the unchanged services run on real data."""
