"""fmu or planner outage (stale state/vehicle, a liveliness token gone, the FC link lost): the
mission holds and resumes only when told to (or by resume_after_outage, never out of a failsafe);
a stalled mission process is not an outage.
"""
from __future__ import annotations

from aeroperception.schemas import LandedState, VehicleState, Vector3
from aeroperception.services.mission.fsm import Config, Event, State
from mission_rig import SURVEY_WPS, Rig, assert_hold, fc, flying, survey, vehicle


def test_stale_vehicle_state_holds_and_waits_for_start_after_it_is_back():
    rig = Rig(Config.from_params(vehicle_timeout_s=0.5))
    rig.to_executing()
    rig.feed(flying(*SURVEY_WPS[0]))
    rig.clear()
    rig.tick(0.3, fresh_state=False)
    assert rig.mgr.state == State.EXECUTING
    rig.tick(0.3, fresh_state=False)                  # 0.6 s without state/vehicle (ticks on time)
    assert rig.mgr.state == State.HOLDING
    assert rig.mgr.transitions[-1] == (State.EXECUTING, Event.FMU_OUTAGE, State.HOLDING)
    assert "fmu outage" in rig.mgr.message
    assert_hold(rig.goals[-1])
    assert not rig.mgr.command("START")[0]            # nothing to resume against yet

    rig.feed(flying(3.0, 0.0, 5.0))                   # fmu is back
    assert rig.mgr.state == State.HOLDING            # default policy: hold until commanded
    assert "holding until commanded" in rig.mgr.message
    assert rig.mgr.command("START")[0]
    assert rig.mgr.state == State.EXECUTING and rig.mgr.wp_index == 1


def test_resume_after_outage_policy_resumes_by_itself():
    rig = Rig(Config.from_params(resume_after_outage=True))
    rig.to_executing()
    rig.silence(1.0)
    assert rig.mgr.state == State.HOLDING
    rig.feed(flying(0.0, 0.0, 5.0))
    assert rig.mgr.state == State.EXECUTING
    assert rig.mgr.transitions[-1] == (State.HOLDING, Event.OUTAGE_RESUME, State.EXECUTING)
    assert "resume_after_outage" in rig.mgr.message


def test_resume_after_outage_does_not_resume_an_operator_hold():
    rig = Rig(Config.from_params(resume_after_outage=True))
    rig.to_executing()
    rig.mgr.command("HOLD")
    rig.silence(1.0)
    rig.feed(flying())
    assert rig.mgr.state == State.HOLDING


def test_fmu_liveliness_gone_holds_at_once():
    rig = Rig()
    rig.to_executing()
    rig.mgr.on_fmu_alive(False, rig.t)
    assert rig.mgr.state == State.HOLDING and "fmu not alive" in rig.mgr.message
    rig.feed(flying())                                # a last sample in flight: still not alive
    assert rig.mgr.outage
    rig.mgr.on_fmu_alive(True, rig.t)
    rig.feed(flying())
    assert not rig.mgr.outage and rig.mgr.state == State.HOLDING


def test_planner_liveliness_gone_holds_until_commanded_or_policy():
    """ARCHITECTURE §8: after a planner outage the vehicle holds until the mission re-checks it."""
    rig = Rig()
    rig.to_executing()
    rig.mgr.on_planner_alive(False, rig.t)
    assert rig.mgr.state == State.HOLDING and "planner not alive" in rig.mgr.message
    rig.feed(flying())
    assert rig.mgr.outage                              # still gone: the outage goes on
    rig.mgr.on_planner_alive(True, rig.t)
    assert not rig.mgr.outage and rig.mgr.state == State.HOLDING   # back, but holds until START
    rig2 = Rig(Config.from_params(resume_after_outage=True))
    rig2.to_executing()
    rig2.mgr.on_planner_alive(False, rig2.t)
    rig2.feed(flying())
    rig2.mgr.on_planner_alive(True, rig2.t)
    assert rig2.mgr.state == State.EXECUTING           # by policy


def test_flight_controller_link_lost_holds():
    rig = Rig()
    rig.to_executing()
    rig.feed(VehicleState(position_m=Vector3(z=5.0), armed=True, landed_state=LandedState.IN_AIR, connected=False))
    assert rig.mgr.state == State.HOLDING and "link lost" in rig.mgr.message


def test_outage_during_a_landing_lets_the_fc_land():
    rig = Rig()
    rig.to_land()
    rig.silence(1.0)
    assert rig.mgr.state == State.LAND and "fmu outage" in rig.mgr.message
    rig.feed(vehicle())
    assert rig.mgr.state == State.IDLE


def test_outage_then_fc_failsafe_landing_ends_idle():
    rig = Rig()
    rig.to_executing()
    rig.silence(1.0)
    rig.feed(fc(z=0.0, mode="RTL", armed=False, landed=LandedState.ON_GROUND))  # FC failsafe landed it
    assert rig.mgr.state == State.IDLE and "landed and disarmed on its own" in rig.mgr.message


def test_perception_recovery_does_not_resume_during_an_outage():
    rig = Rig()
    rig.to_executing(survey(require_vio=True))
    rig.tick(healthy=True)
    rig.tick(healthy=False)
    assert rig.mgr.hold_reason == "perception"
    rig.silence(1.0, step=0.25)                       # perception still unhealthy, then fmu goes silent
    assert rig.mgr.outage and rig.mgr.state == State.HOLDING
    rig.tick(0.1, healthy=True, fresh_state=False)    # perception is back, fmu is not
    assert rig.mgr.state == State.HOLDING


def test_resume_after_outage_never_takes_the_vehicle_out_of_a_failsafe_rtl():
    rig = Rig(Config.from_params(resume_after_outage=True))
    rig.to_executing()
    rig.silence(1.0)
    rig.feed(fc(mode="RTL"))                          # the FC's offboard-loss failsafe is flying home
    assert rig.mgr.state == State.HOLDING and "OFFBOARD" not in rig.bridge.modes()[1:]


def test_a_stalled_mission_process_is_not_an_fmu_outage():
    rig = Rig(Config.from_params(vehicle_timeout_s=0.5))
    rig.to_executing()
    rig.tick(0.1)
    rig.tick(2.0, fresh_state=False)                  # our own tick was 2 s late: we stalled, not fmu
    assert rig.mgr.state == State.EXECUTING and not rig.mgr.outage
    rig.tick(0.1, fresh_state=False)                  # on time again: the backlog may still be on its way
    assert rig.mgr.state == State.EXECUTING and not rig.mgr.outage
    rig.tick(0.45, fresh_state=False)                 # 0.55 s awake and still no state: outage
    assert rig.mgr.state == State.HOLDING and "fmu outage" in rig.mgr.message


def test_a_stall_whose_backlog_arrives_a_few_ticks_late_never_holds():
    """A loaded host: the mission stopped 0.7 s, then both its timers ran before the subscriber
    thread delivered the queued states (0.3 s later): no hold, so the planner never brakes to a
    stop mid-path (the figure-8 at 3 m/s stopped dead from 2.8-3.0 m/s this way)."""
    rig = Rig(Config.from_params(vehicle_timeout_s=0.5))
    rig.to_executing()
    rig.tick(0.1)
    before = len(rig.mgr.transitions)
    rig.tick(0.7, fresh_state=False)                  # the stall
    for _ in range(3):
        rig.tick(0.1, fresh_state=False)              # timers on time, the backlog not delivered yet
        assert rig.mgr.state == State.EXECUTING and not rig.mgr.outage
    rig.tick(0.1)                                     # the backlog
    assert rig.mgr.state == State.EXECUTING and not rig.mgr.outage
    assert rig.mgr.transitions[before:] == []


def stamped(st: VehicleState, t_s: float) -> VehicleState:
    st.header.stamp_ns = int(t_s * 1e9)
    return st


def test_state_late_but_not_missing_resumes_by_itself():
    """fmu stamped every sample on time; they reached us 0.6 s late in a burst (a stall between):
    the hold ends by itself once the next stamp in sequence arrives."""
    rig = Rig(Config.from_params(vehicle_timeout_s=0.5))
    rig.to_executing()
    rig.feed(stamped(flying(*SURVEY_WPS[0]), 100.00))
    rig.tick(0.3, fresh_state=False)
    rig.tick(0.3, fresh_state=False)
    assert rig.mgr.state == State.HOLDING and "fmu outage" in rig.mgr.message
    rig.feed(stamped(flying(*SURVEY_WPS[0]), 100.02))  # the backlog: the next stamp after the last one
    assert rig.mgr.state == State.EXECUTING and not rig.mgr.outage
    assert rig.mgr.transitions[-1] == (State.HOLDING, Event.OUTAGE_RESUME, State.EXECUTING)
    assert "late, not missing" in rig.mgr.message


def test_state_with_a_gap_in_its_stamps_is_an_outage_and_holds():
    rig = Rig(Config.from_params(vehicle_timeout_s=0.5))
    rig.to_executing()
    rig.feed(stamped(flying(*SURVEY_WPS[0]), 100.00))
    rig.silence(1.0)
    rig.feed(stamped(flying(*SURVEY_WPS[0]), 101.00))  # fmu itself stopped for 1 s (or restarted)
    assert rig.mgr.state == State.HOLDING and "holding until commanded" in rig.mgr.message


def test_late_state_never_resumes_out_of_an_operator_hold_or_a_failsafe():
    rig = Rig(Config.from_params(vehicle_timeout_s=0.5))
    rig.to_executing()
    rig.mgr.command("HOLD")
    rig.feed(stamped(flying(), 100.00))
    rig.silence(1.0)
    rig.feed(stamped(flying(), 100.02))
    assert rig.mgr.state == State.HOLDING
    rig = Rig(Config.from_params(vehicle_timeout_s=0.5))
    rig.to_executing()
    rig.feed(stamped(fc(), 100.00))
    rig.silence(1.0)
    rig.feed(stamped(fc(mode="RTL"), 100.02))
    assert rig.mgr.state == State.HOLDING
