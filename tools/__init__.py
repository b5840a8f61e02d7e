"""The `aero` command and its benches, evals and harnesses."""
# The services' process-wide native settings (one OpenBLAS thread: its workers busy-wait) hold
# for `aero` too, so a bench or eval runs the services' code as the services run it. Imported
# first thing, before anything loads numpy.
from aeroperception import services as _services  # noqa: F401
