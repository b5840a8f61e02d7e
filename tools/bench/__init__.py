"""Benchmarks: `aero bench ...` measurements, each printing median, p99 and a ratio to a baseline."""
