"""viz: the Rerun live view of the stack (and .rrd recordings of it).

Opt-in, read-only: it subscribes to the stack's keys, samples each at its own rate and converts
them to Rerun archetypes on newest-wins workers, so a slow or absent viewer costs dropped data
(counted in diagnostics/viz), never latency elsewhere.
"""
