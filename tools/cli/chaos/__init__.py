"""`aero chaos`: fault injection against a running sim stack, one fault per row, and a figures table.

Each row starts from the ground, flies a mission (survey_01 by default), injects one fault mid-leg
(kill -9 of a service, router kill, FC link loss, ground-station loss, SIGSTOP hang, clock jump;
FC reboot on the ground), observes what the stack and the vehicle do, and judges two things:
the row's expected outcome and whether the vehicle stayed safe by the simulator's ground truth
(sim/truth/state): no ground impact at speed, inside the geofence, every setpoint the flight
controller received finite and inside the envelope, and at the end either holding, landed and
disarmed, or flying the mission normally.

    row          what a row is (Row, Ctx) and the observations rows share
    rows         the fault table (build_rows): inject / expected / observe per fault
    ground_station  the stand-in ground station of the gcs-loss row
    judging      safety by the truth (judge_safety) and a row's result
    running      run_row (fly, inject, observe, judge) and the table
    cli          the `aero chaos` command

The stack is the harness's `SimStack` (aeroperception.tools.harness): `aero up --profile sim` on
free ports with a MavlinkTap relaying sim <-> fmu in this process, so a row can cut the FC link,
speak to the FC (reboot) and check every SET_POSITION_TARGET_LOCAL_NED fmu sends. tests/faults and
`aero bench soak` use the same class. Every process is stopped by its own pid, never by name.
"""
from .cli import DEFAULT_MISSION, register, run
from .judging import AT_REST_MPS, RowResult, judge_safety
from .rows import build_rows
from .running import format_table, run_row

__all__ = ["AT_REST_MPS", "DEFAULT_MISSION", "RowResult", "build_rows", "format_table",
           "judge_safety", "register", "run", "run_row"]
