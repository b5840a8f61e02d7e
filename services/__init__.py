"""The stack's services, each started as `python -m aeroperception.services.<name>`, and the
libraries they are built on (LIBRARIES: no contract, no process; tests/unit/test_import_rules.py).

This module runs before anything a service imports, so it is where process-wide native
settings go. OpenBLAS (numpy's BLAS) starts one worker per core and its workers busy-wait
between calls: a service doing small products on every scan or frame (the lidar pipeline's
(N, 3) @ (3, 3)) paid twice its CPU time for no speed-up, and on a shared 2-core machine the
spinning took cores from everything else. Services are single-threaded numpy users; a user
who wants more threads sets the variable before starting the stack.
"""
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# The packages here that are libraries, not services: the algorithms services share, the runtime,
# the MAVLink (NED/FRD) boundary.
LIBRARIES = ("lib", "runtime", "mavlink")
