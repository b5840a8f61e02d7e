"""Mission FSM (services/mission/fsm.py): the transition table, its entry side effects, the
ERROR path, the perception policy and a whole nominal flight, driven with plain objects.

The only double is FakeBridge, the flight-controller calls the FSM takes by design (a Bridge
protocol): it records every call and answers ok, fails, or holds the answer for later.
"""
from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np
import pytest

from aeroperception.schemas import LandedState, Mission, VehicleState, Vector3, parse_mission
from aeroperception.services.mission.fsm import (
    TRANSITIONS, Config, Event, GoalOut, MissionManager, State,
)
from aeroperception.services.planner.logic import Goal, WaypointPlanner

ROOT = Path(__file__).resolve().parents[2]
SURVEY_01 = ROOT / "examples" / "missions" / "survey_01.json"
# seed 000 §5.1: survey_01's waypoints, takeoff 5 m, acceptance 0.5 m
SURVEY_WPS = [(0.0, 0.0, 5.0), (10.0, 0.0, 5.0), (10.0, 10.0, 5.0), (0.0, 0.0, 5.0)]


class FakeBridge:
    """Records arm/set_mode calls. Answers at once with success unless the call is listed in
    `fail` ({("set_mode", "LAND"): "denied"}); with `defer=True` answers wait in `pending`."""

    def __init__(self, defer: bool = False):
        self.calls: list[tuple[str, object]] = []
        self.fail: dict[tuple[str, object], str] = {}
        self.defer = defer
        self.pending: list[tuple[tuple[str, object], object]] = []

    def arm(self, arm, done) -> None:
        self._call(("arm", arm), done)

    def set_mode(self, mode, done) -> None:
        self._call(("set_mode", mode), done)

    def _call(self, key, done) -> None:
        self.calls.append(key)
        if self.defer:
            self.pending.append((key, done))
        else:
            self._answer(key, done)

    def _answer(self, key, done) -> None:
        if key in self.fail:
            done(False, self.fail[key])
        else:
            done(True, "ok")

    def answer_pending(self) -> None:
        pending, self.pending = self.pending, []
        for key, done in pending:
            self._answer(key, done)

    def modes(self) -> list:
        return [arg for kind, arg in self.calls if kind == "set_mode"]

    def arms(self) -> list:
        return [arg for kind, arg in self.calls if kind == "arm"]


def vehicle(x=0.0, y=0.0, z=0.0, armed=False, landed=LandedState.ON_GROUND, connected=True, yaw=0.0):
    return VehicleState(position_m=Vector3(x=x, y=y, z=z), armed=armed, landed_state=landed,
                        connected=connected, yaw_rad=yaw)


def flying(x=0.0, y=0.0, z=5.0):
    return vehicle(x, y, z, armed=True, landed=LandedState.IN_AIR)


def survey(**changes) -> Mission:
    m = parse_mission(SURVEY_01.read_text())
    return msgspec.structs.replace(m, **changes) if changes else m


class Rig:
    """A MissionManager with a FakeBridge, every published goal, results and a clock."""

    def __init__(self, config: Config | None = None, bridge: FakeBridge | None = None):
        self.bridge = bridge or FakeBridge()
        self.goals: list[GoalOut] = []
        self.results: list[tuple[bool, str]] = []
        self.mgr = MissionManager(self.bridge, self.goals.append, config)
        self.t = 100.0

    def on_result(self, ok, msg) -> None:
        self.results.append((ok, msg))

    def feed(self, st: VehicleState, dt: float = 0.02) -> None:
        self.t += dt
        self.mgr.on_vehicle(st, self.t)

    def tick(self, dt: float = 0.5, healthy: bool | None = None) -> None:
        self.t += dt
        if healthy is not None:
            self.mgr.on_perception(healthy, self.t)
        self.mgr.tick(self.t)

    def clear(self) -> None:
        self.bridge.calls.clear()
        self.goals.clear()
        self.results.clear()

    # ---- drive the manager into a state through its real inputs

    def to_idle(self, mission: Mission | None = None) -> None:
        self.feed(vehicle())
        ok, msg = self.mgr.load(mission or survey())
        assert ok, msg
        assert self.mgr.state == State.IDLE

    def to_takeoff(self, mission: Mission | None = None) -> None:
        self.to_idle(mission)
        ok, msg = self.mgr.command("TAKEOFF", self.on_result)
        assert ok, msg
        self.feed(vehicle(z=0.5, armed=True, landed=LandedState.IN_AIR))
        assert self.mgr.state == State.TAKEOFF

    def to_holding(self, mission: Mission | None = None) -> None:
        self.to_takeoff(mission)
        self.feed(flying(z=5.0))
        assert self.mgr.state == State.HOLDING

    def to_executing(self, mission: Mission | None = None) -> None:
        self.to_holding(mission)
        ok, msg = self.mgr.command("START", self.on_result)
        assert ok, msg
        assert self.mgr.state == State.EXECUTING

    def to_land(self, mission: Mission | None = None) -> None:
        self.to_executing(mission)
        ok, msg = self.mgr.command("LAND", self.on_result)
        assert ok, msg
        assert self.mgr.state == State.LAND

    def to(self, state: State, mission: Mission | None = None) -> None:
        getattr(self, f"to_{state.value.lower()}")(mission)


def assert_goal(goal: GoalOut, position, yaw=None) -> None:
    assert goal.position_m is not None, "expected a goal, got hold"
    np.testing.assert_allclose(goal.position_m, position, atol=1e-9)
    if yaw is not None:
        assert goal.yaw_rad == pytest.approx(yaw)


def assert_hold(goal: GoalOut) -> None:
    assert goal.position_m is None, f"expected hold, got goal {goal.position_m}"


# ================================================================ the table, entry by entry

TABLE = sorted(TRANSITIONS.items(), key=lambda kv: (kv[0][0].value, kv[0][1].value))


@pytest.mark.parametrize(("src", "event", "dst"), [(s, e, d) for (s, e), d in TABLE],
                         ids=[f"{s.value}-{e.value}-{d.value}" for (s, e), d in TABLE])
def test_every_table_transition_reaches_its_target_with_entry_side_effects(src, event, dst):
    rig = Rig()
    rig.to(src)
    rig.clear()

    assert rig.mgr.fire(event, "test") is True
    assert rig.mgr.state == dst
    assert rig.mgr.transitions[-1] == (src, event, dst)
    assert rig.mgr.status().state == dst.value

    if dst == State.TAKEOFF:
        # climb straight up to the mission's takeoff altitude, and ask for OFFBOARD
        assert len(rig.goals) == 1
        assert_goal(rig.goals[0], [0.0, 0.0, 5.0])
        assert rig.bridge.calls == [("set_mode", "OFFBOARD")]
    elif dst == State.HOLDING:
        assert len(rig.goals) == 1
        assert_hold(rig.goals[0])  # (a finished goto holds at its target: see the goto tests)
        # leaving AUTO.LAND needs OFFBOARD back; otherwise we are already in OFFBOARD
        expected = [("set_mode", "OFFBOARD")] if src == State.LAND else []
        assert rig.bridge.calls == expected
    elif dst == State.EXECUTING:
        assert len(rig.goals) == 1
        assert_goal(rig.goals[0], SURVEY_WPS[0], yaw=0.0)
        assert rig.bridge.calls == []
    elif dst == State.LAND:
        mode = "RTL" if event in (Event.RTL_CMD, Event.PERCEPTION_TIMEOUT) else "LAND"
        assert rig.bridge.calls == [("set_mode", mode)]
        assert rig.mgr.land_mode == mode
        assert rig.goals == []
    elif dst == State.IDLE:
        assert len(rig.goals) == 1
        assert_hold(rig.goals[0])
        assert rig.bridge.calls == []
    else:  # pragma: no cover - a new state needs its entry side effects pinned here
        pytest.fail(f"no entry expectations for {dst}")


def test_table_covers_every_state_and_event_is_used():
    assert {s for s, _ in TRANSITIONS} | set(TRANSITIONS.values()) == set(State)
    assert {e for _, e in TRANSITIONS} == set(Event)


UNLISTED = [(s, e) for s in State for e in Event if (s, e) not in TRANSITIONS]


@pytest.mark.parametrize(("src", "event"), UNLISTED, ids=[f"{s.value}-{e.value}" for s, e in UNLISTED])
def test_events_not_in_the_table_are_ignored(src, event):
    rig = Rig()
    rig.to(src)
    before = list(rig.mgr.transitions)
    rig.clear()

    assert rig.mgr.fire(event, "test") is False
    assert rig.mgr.state == src
    assert rig.mgr.transitions == before
    assert rig.goals == [] and rig.bridge.calls == []


# ================================================================ ERROR path (failed bridge calls)

def test_failed_land_request_in_the_air_holds_and_reports_the_reason():
    rig = Rig(bridge=FakeBridge(defer=True))
    rig.to_idle()
    rig.mgr.command("TAKEOFF", rig.on_result)
    rig.bridge.answer_pending()                       # arm ok -> TAKEOFF, OFFBOARD asked
    rig.bridge.answer_pending()                       # OFFBOARD ok
    rig.feed(flying(z=5.0))
    rig.mgr.command("START")
    rig.feed(flying(z=5.0))                           # waypoint 0 reached
    assert rig.mgr.state == State.EXECUTING
    rig.bridge.fail[("set_mode", "LAND")] = "mode change denied"
    rig.clear()

    rig.mgr.command("LAND")
    assert rig.mgr.state == State.LAND
    rig.bridge.answer_pending()                       # the FC says no

    assert rig.mgr.state == State.HOLDING
    assert rig.mgr.transitions[-1] == (State.LAND, Event.BRIDGE_FAILED_AIR, State.HOLDING)
    status = rig.mgr.status()
    assert status.state == "HOLDING"
    assert "LAND failed" in status.message and "mode change denied" in status.message
    assert_hold(rig.goals[-1])
    assert rig.bridge.modes() == ["LAND", "OFFBOARD"]  # and take control back


def test_failed_offboard_during_takeoff_in_the_air_holds():
    rig = Rig(bridge=FakeBridge(defer=True))
    rig.to_idle()
    rig.mgr.command("TAKEOFF", rig.on_result)
    rig.bridge.answer_pending()                       # arm ok -> TAKEOFF, OFFBOARD pending
    assert rig.mgr.state == State.TAKEOFF
    rig.feed(flying(z=1.0))                           # already off the ground
    rig.bridge.fail[("set_mode", "OFFBOARD")] = "no setpoint stream"
    rig.bridge.answer_pending()

    assert rig.mgr.state == State.HOLDING
    assert "OFFBOARD failed: no setpoint stream" in rig.mgr.status().message


def test_failed_offboard_on_the_ground_goes_back_to_idle():
    rig = Rig(bridge=FakeBridge(defer=True))
    rig.to_idle()
    rig.mgr.command("TAKEOFF", rig.on_result)
    rig.bridge.answer_pending()                       # arm ok -> TAKEOFF
    rig.feed(vehicle(armed=True, landed=LandedState.ON_GROUND))
    rig.bridge.fail[("set_mode", "OFFBOARD")] = "no setpoint stream"
    rig.goals.clear()
    rig.bridge.answer_pending()

    assert rig.mgr.state == State.IDLE
    assert rig.mgr.transitions[-1] == (State.TAKEOFF, Event.BRIDGE_FAILED_GROUND, State.IDLE)
    assert "OFFBOARD failed: no setpoint stream" in rig.mgr.status().message
    assert_hold(rig.goals[-1])


def test_failed_offboard_when_aborting_a_landing_stays_holding_and_reports():
    rig = Rig()
    rig.to_land()
    rig.bridge.fail[("set_mode", "OFFBOARD")] = "denied"
    rig.mgr.command("HOLD")                           # LAND -> HOLDING asks for OFFBOARD: refused
    assert rig.mgr.state == State.HOLDING             # no table entry for HOLDING + failure
    assert rig.mgr.status().message == "OFFBOARD failed: denied"


def test_arm_refused_stays_idle_and_reports():
    rig = Rig()
    rig.to_idle()
    rig.bridge.fail[("arm", True)] = "preflight checks failed"

    accepted, _ = rig.mgr.command("TAKEOFF", rig.on_result)

    assert accepted  # accepted at once; the outcome comes through on_result
    assert rig.mgr.state == State.IDLE
    assert rig.bridge.calls == [("arm", True)]        # no mode request after a refused arm
    assert rig.results == [(False, "arming failed: preflight checks failed")]
    assert "preflight checks failed" in rig.mgr.status().message
    assert rig.mgr.transitions == []


def test_arm_command_refusal_is_reported_through_on_result():
    rig = Rig()
    rig.to_idle()
    rig.bridge.fail[("arm", True)] = "throttle not low"
    rig.mgr.command("ARM", rig.on_result)
    assert rig.results == [(False, "throttle not low")]
    assert rig.mgr.state == State.IDLE


def test_takeoff_refused_without_a_connected_vehicle():
    rig = Rig()
    rig.feed(vehicle(connected=False))
    accepted, msg = rig.mgr.command("TAKEOFF", rig.on_result)
    assert not accepted and "no vehicle state" in msg
    assert rig.bridge.calls == [] and rig.mgr.state == State.IDLE


def test_takeoff_when_already_armed_does_not_arm_again():
    rig = Rig()
    rig.to_idle()
    rig.feed(vehicle(armed=True))
    rig.mgr.command("TAKEOFF", rig.on_result)
    assert rig.bridge.calls == [("set_mode", "OFFBOARD")]
    assert rig.mgr.state == State.TAKEOFF
    assert rig.results == [(True, "taking off")]


# ================================================================ nominal flight

def test_nominal_survey_01_flight_idle_to_idle():
    rig = Rig()
    mgr, bridge = rig.mgr, rig.bridge
    rig.feed(vehicle())
    ok, msg = mgr.load(parse_mission(SURVEY_01.read_text()))
    assert ok and "survey_01" in msg and "4 waypoints" in msg

    # TAKEOFF: arms through the bridge, then asks for OFFBOARD, goal straight above at 5 m
    accepted, _ = mgr.command("TAKEOFF", rig.on_result)
    assert accepted and mgr.state == State.TAKEOFF
    assert bridge.calls == [("arm", True), ("set_mode", "OFFBOARD")]
    assert rig.results == [(True, "taking off")]
    assert_goal(rig.goals[-1], [0.0, 0.0, 5.0])

    # START during the climb is remembered, not refused
    accepted, msg = mgr.command("START", rig.on_result)
    assert accepted and mgr.state == State.TAKEOFF and "when takeoff completes" in msg
    for z in (0.2, 1.5, 3.0, 4.5):
        rig.feed(vehicle(z=z, armed=True, landed=LandedState.IN_AIR))
        assert mgr.state == State.TAKEOFF
    rig.feed(flying(z=4.85))                          # within the 0.3 m tolerance
    assert mgr.state == State.EXECUTING
    assert_goal(rig.goals[-1], SURVEY_WPS[0], yaw=0.0)

    # fly the square: each waypoint fires once, as the position gets there
    path = [(0.0, 0.0, 5.0), (4.0, 0.0, 5.0), (9.7, 0.1, 5.0), (10.0, 5.0, 5.0), (10.1, 9.8, 5.0),
            (5.0, 5.0, 5.0), (0.2, -0.2, 5.0)]
    reached_after = [[0], [0], [0, 1], [0, 1], [0, 1, 2], [0, 1, 2], [0, 1, 2, 3]]
    for pos, want in zip(path, reached_after):
        rig.feed(flying(*pos))
        assert mgr.reached_events == want, pos
    assert [tuple(g.position_m) for g in rig.goals if g.position_m is not None][-4:] == SURVEY_WPS

    # mission complete -> LAND via the flight controller's LAND mode
    assert mgr.state == State.LAND
    assert bridge.calls[-1] == ("set_mode", "LAND")
    rig.feed(vehicle(z=2.0, armed=True, landed=LandedState.LANDING))
    rig.feed(vehicle(z=0.0, armed=True, landed=LandedState.ON_GROUND))
    assert mgr.state == State.LAND
    rig.feed(vehicle(z=0.0, armed=False, landed=LandedState.ON_GROUND))
    assert mgr.state == State.IDLE

    states = [mgr.transitions[0][0]] + [dst for _, _, dst in mgr.transitions]
    assert states == [State.IDLE, State.TAKEOFF, State.HOLDING, State.EXECUTING, State.LAND, State.IDLE]
    assert [e for _, e, _ in mgr.transitions] == [
        Event.TAKEOFF_CMD, Event.ALTITUDE_REACHED, Event.START_CMD, Event.WAYPOINTS_DONE, Event.LANDED]
    assert mgr.status().state == "IDLE"
    assert bridge.arms() == [True]                    # the FC disarmed itself: no disarm sent


def test_mission_can_be_flown_again_after_it_completed():
    rig = Rig()
    rig.to_executing()
    for wp in SURVEY_WPS:
        rig.feed(flying(*wp))
    assert rig.mgr.reached_events == [0, 1, 2, 3] and rig.mgr.state == State.LAND
    rig.feed(vehicle())                               # landed, disarmed
    assert rig.mgr.state == State.IDLE

    rig.mgr.command("TAKEOFF", rig.on_result)
    rig.mgr.command("START", rig.on_result)
    rig.feed(flying(z=5.0))
    assert rig.mgr.state == State.EXECUTING
    assert rig.mgr.status().active_waypoint == 0
    assert_goal(rig.goals[-1], SURVEY_WPS[0])


def test_completed_mission_holds_when_land_on_complete_is_off_and_start_restarts_it():
    rig = Rig(Config(land_on_complete=False))
    rig.to_executing()
    for wp in SURVEY_WPS:
        rig.feed(flying(*wp))
    assert rig.mgr.state == State.HOLDING
    assert rig.bridge.modes() == ["OFFBOARD"]         # no LAND requested
    rig.mgr.command("START", rig.on_result)
    assert rig.mgr.state == State.EXECUTING
    assert_goal(rig.goals[-1], SURVEY_WPS[0])


def test_mission_and_planner_fly_survey_01_closed_loop():
    """The planner's velocity setpoints, integrated, carry the vehicle through every waypoint."""
    rig = Rig()
    planner = WaypointPlanner()
    goals_seen = 0
    rig.to_idle()
    rig.mgr.command("TAKEOFF", rig.on_result)
    rig.mgr.command("START", rig.on_result)
    pos, dt = np.zeros(3), 0.02
    for _ in range(20_000):
        if len(rig.goals) > goals_seen:
            g = rig.goals[-1]
            goals_seen = len(rig.goals)
            planner.set_goal(None if g.position_m is None else Goal(g.position_m, g.yaw_rad, goals_seen))
        if rig.mgr.state == State.LAND:
            break
        sp = planner.step(pos, 0.0).setpoint
        if sp.velocity_valid and not sp.position_valid:
            pos = pos + sp.velocity_mps.to_array() * dt
        rig.feed(flying(*pos), dt)
    assert rig.mgr.state == State.LAND
    assert rig.mgr.reached_events == [0, 1, 2, 3]
    assert rig.t - 100.0 < 60.0                       # ~45 m at <= 2 m/s


# ================================================================ perception policy

def test_perception_loss_while_executing_holds_and_recovery_resumes_the_same_waypoint():
    rig = Rig()
    rig.to_executing(survey(require_vio=True))
    rig.tick(healthy=True)
    rig.feed(flying(0.0, 0.0, 5.0))                   # waypoint 0 reached, flying to 1
    assert rig.mgr.wp_index == 1 and rig.mgr.state == State.EXECUTING
    rig.clear()

    rig.tick(healthy=False)
    assert rig.mgr.state == State.HOLDING
    assert rig.mgr.hold_reason == "perception"
    assert "perception" in rig.mgr.status().message
    assert_hold(rig.goals[-1])
    rig.feed(flying(3.0, 0.0, 5.0))                   # positions while holding change nothing
    assert rig.mgr.reached_events == [0]

    for _ in range(8):                                # 4 s still unhealthy
        rig.tick(0.5, healthy=False)
        assert rig.mgr.state == State.HOLDING
    rig.tick(0.5, healthy=True)                       # back well within 10 s
    assert rig.mgr.state == State.EXECUTING
    assert rig.mgr.wp_index == 1
    assert_goal(rig.goals[-1], SURVEY_WPS[1])
    assert rig.bridge.calls == []


def test_perception_not_back_within_recovery_time_lands_with_rtl():
    rig = Rig()
    rig.to_executing(survey(require_vio=True))
    rig.tick(healthy=True)
    rig.tick(healthy=False)
    assert rig.mgr.state == State.HOLDING
    t_hold = rig.t
    while rig.t - t_hold < 9.9:
        rig.tick(0.5, healthy=False)
        assert rig.mgr.state == State.HOLDING, rig.t - t_hold
    rig.tick(0.6, healthy=False)                      # > perception_recovery_s (10 s)

    assert rig.mgr.state == State.LAND
    assert rig.mgr.transitions[-1] == (State.HOLDING, Event.PERCEPTION_TIMEOUT, State.LAND)
    assert rig.mgr.land_mode == "RTL"
    assert rig.bridge.calls[-1] == ("set_mode", "RTL")


def test_silent_perception_counts_as_unhealthy():
    rig = Rig()
    rig.to_executing(survey(require_vio=True))
    rig.tick(0.5, healthy=True)
    rig.tick(2.0)
    assert rig.mgr.state == State.EXECUTING
    rig.tick(1.5)                                     # 3.5 s without perception/health
    assert rig.mgr.state == State.HOLDING and rig.mgr.hold_reason == "perception"


def test_unhealthy_perception_is_ignored_when_not_required():
    rig = Rig()
    rig.to_executing(survey(require_vio=False))
    for _ in range(30):
        rig.tick(0.5, healthy=False)
    assert rig.mgr.state == State.EXECUTING


def test_config_require_perception_applies_when_the_mission_does_not_say():
    rig = Rig(Config(require_perception=True))
    rig.to_executing(survey())
    rig.tick(healthy=False)
    assert rig.mgr.state == State.HOLDING


def test_operator_hold_is_not_resumed_by_healthy_perception():
    rig = Rig()
    rig.to_executing(survey(require_vio=True))
    rig.tick(healthy=True)
    rig.mgr.command("HOLD")
    for _ in range(30):
        rig.tick(0.5, healthy=True)
    assert rig.mgr.state == State.HOLDING


# ================================================================ operator inputs

def test_mission_load_is_rejected_while_executing():
    rig = Rig()
    rig.to_executing()
    other = survey(mission_id="other", waypoints=[{"x": 1.0, "y": 1.0, "z": 2.0}])
    ok, msg = rig.mgr.load(msgspec.convert(msgspec.to_builtins(other), Mission))
    assert not ok and "EXECUTING" in msg
    assert rig.mgr.mission.mission_id == "survey_01"
    assert rig.mgr.state == State.EXECUTING


def test_mission_load_in_holding_replaces_the_mission_from_its_first_waypoint():
    rig = Rig()
    rig.to_executing()
    rig.feed(flying(0.0, 0.0, 5.0))
    rig.mgr.command("HOLD")
    other = parse_mission('{"mission_id": "other", "waypoints": [{"x": 1, "y": 2, "z": 3}]}')
    ok, _ = rig.mgr.load(other)
    assert ok and rig.mgr.wp_index == -1
    rig.mgr.command("START")
    assert_goal(rig.goals[-1], [1.0, 2.0, 3.0])


def test_invalid_mission_json_never_reaches_the_manager():
    from aeroperception.schemas import SchemaError
    with pytest.raises(SchemaError, match="waypoints"):
        parse_mission('{"mission_id": "bad", "waypoints": []}')
    with pytest.raises(SchemaError, match=r"\$\.waypoints\[0\]\.x"):
        parse_mission('{"waypoints": [{"x": "a", "y": 0, "z": 1}]}')


def test_start_without_a_mission_is_refused():
    rig = Rig()
    rig.feed(vehicle())
    ok, msg = rig.mgr.command("START", rig.on_result)
    assert not ok and "no mission" in msg
    assert rig.results == [(False, msg)]


def test_start_from_idle_is_refused():
    rig = Rig()
    rig.to_idle()
    ok, msg = rig.mgr.command("START")
    assert not ok and "TAKEOFF first" in msg and rig.mgr.state == State.IDLE


def test_unknown_command_is_refused():
    rig = Rig()
    ok, msg = rig.mgr.command("FLIP", rig.on_result)
    assert not ok and "unknown command" in msg


def test_goto_from_holding_executes_then_holds_when_reached():
    rig = Rig()
    rig.to_holding()
    rig.clear()
    ok, _ = rig.mgr.goto(np.array([3.0, 4.0, 6.0]), 0.5)
    assert ok and rig.mgr.state == State.EXECUTING
    assert_goal(rig.goals[-1], [3.0, 4.0, 6.0], yaw=0.5)
    assert rig.mgr.distance_to_goal_m() == pytest.approx(math.sqrt(9 + 16 + 1))

    rig.feed(flying(1.5, 2.0, 5.5))
    assert rig.mgr.state == State.EXECUTING
    rig.feed(flying(2.9, 3.9, 6.0))                   # inside 0.5 m
    assert rig.mgr.state == State.HOLDING
    assert rig.mgr.transitions[-1] == (State.EXECUTING, Event.GOTO_DONE, State.HOLDING)
    assert rig.mgr.goto_target is None
    assert_goal(rig.goals[-1], [3.0, 4.0, 6.0], yaw=0.5)  # holds at the target, not 0.5 m short
    assert rig.mgr.reached_events == []               # no mission waypoint was flown


def test_goto_needs_the_vehicle_in_the_air():
    rig = Rig()
    rig.to_idle()
    ok, msg = rig.mgr.goto(np.array([1.0, 1.0, 1.0]), None)
    assert not ok and rig.mgr.state == State.IDLE and rig.goals == []


def test_disarm_is_refused_in_the_air():
    rig = Rig()
    rig.to_executing()
    rig.feed(flying(0.0, 0.0, 5.0))
    rig.clear()
    ok, msg = rig.mgr.command("DISARM", rig.on_result)
    assert not ok and "in the air" in msg
    assert rig.bridge.calls == []
    assert rig.results == [(False, msg)]


def test_disarm_on_the_ground_goes_to_the_bridge():
    rig = Rig()
    rig.feed(vehicle(armed=True))
    ok, _ = rig.mgr.command("DISARM", rig.on_result)
    assert ok and rig.bridge.calls == [("arm", False)]
    assert rig.results == [(True, "ok")]


def test_land_disarms_if_still_armed_on_the_ground_after_the_grace_period():
    rig = Rig()
    rig.to_land()
    rig.clear()
    rig.feed(vehicle(z=0.0, armed=True, landed=LandedState.ON_GROUND), dt=1.0)
    t0 = rig.t
    rig.feed(vehicle(armed=True), dt=4.9)             # 4.9 s on the ground
    assert rig.bridge.calls == []
    rig.feed(vehicle(armed=True), dt=0.2)             # 5.1 s > disarm_after_landing_s
    assert rig.t - t0 > rig.mgr.cfg.disarm_after_landing_s
    assert rig.bridge.calls == [("arm", False)]
    rig.feed(vehicle(armed=True), dt=1.0)             # sent once
    assert rig.bridge.calls == [("arm", False)]
    rig.feed(vehicle(armed=False))
    assert rig.mgr.state == State.IDLE


def test_land_grace_period_restarts_if_the_vehicle_bounces():
    rig = Rig()
    rig.to_land()
    rig.clear()
    rig.feed(vehicle(armed=True), dt=1.0)
    rig.feed(vehicle(armed=True), dt=4.0)
    rig.feed(vehicle(z=0.3, armed=True, landed=LandedState.IN_AIR), dt=0.5)
    rig.feed(vehicle(armed=True), dt=0.5)
    rig.feed(vehicle(armed=True), dt=4.0)
    assert rig.bridge.calls == []


def test_rtl_command_lands_through_rtl_mode_and_hold_aborts_it():
    rig = Rig()
    rig.to_executing()
    rig.clear()
    rig.mgr.command("RTL")
    assert rig.mgr.state == State.LAND and rig.bridge.calls == [("set_mode", "RTL")]
    rig.mgr.command("HOLD")
    assert rig.mgr.state == State.HOLDING
    assert rig.bridge.calls[-1] == ("set_mode", "OFFBOARD")


def test_link_loss_while_executing_holds():
    rig = Rig()
    rig.to_executing()
    rig.mgr.on_link(False)
    assert rig.mgr.state == State.HOLDING and rig.mgr.hold_reason == "link"


def test_status_reports_progress():
    rig = Rig()
    rig.to_executing()
    rig.feed(flying(0.0, 0.0, 5.0))
    rig.feed(flying(4.0, 0.0, 5.0))
    st = rig.mgr.status()
    assert (st.mission_id, st.state, st.active_waypoint, st.total_waypoints) == ("survey_01", "EXECUTING", 1, 4)
    assert st.distance_to_goal_m == pytest.approx(6.0)
    assert st.elapsed_time_s > 0


def test_goto_uses_the_goals_own_acceptance_radius():
    rig = Rig()
    rig.to_holding()
    ok, _ = rig.mgr.goto(np.array([3.0, 4.0, 6.0]), None, acceptance_radius_m=2.0)
    assert ok and rig.mgr.state == State.EXECUTING
    rig.feed(flying(2.0, 3.0, 5.5))                   # 1.5 m away: inside 2.0, outside the mission's 0.5
    assert rig.mgr.state == State.HOLDING
