"""The mission FSM's test rig: a MissionManager driven through its real inputs with plain
objects. The only double is FakeBridge, the flight-controller calls the FSM takes by design (a
Bridge protocol): it records every call and answers ok, fails, or holds the answer for later."""
from __future__ import annotations

from pathlib import Path

import msgspec
import numpy as np
import pytest

from aeroperception.schemas import LandedState, Mission, VehicleState, Vector3, parse_mission
from aeroperception.services.mission.fsm import Config, GoalOut, MissionManager, State
from aeroperception.services.mission.requests import Outcome

ROOT = Path(__file__).resolve().parents[1]
SURVEY_01 = ROOT / "examples" / "missions" / "survey_01.json"
# survey_01's waypoints (takeoff 5 m, acceptance 0.5 m)
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

    def __init__(self, config: Config | None = None, bridge: FakeBridge | None = None, limits=None):
        self.bridge = bridge or FakeBridge()
        self.goals: list[GoalOut] = []
        self.outcomes: list[Outcome] = []
        self.mgr = MissionManager(self.bridge, self.goals.append, config, limits=limits)
        self.t = 100.0

    def outcome(self) -> Outcome:
        """A new Outcome for one request, kept so `results` can show how it ended."""
        self.outcomes.append(Outcome())
        return self.outcomes[-1]

    @property
    def results(self) -> list[tuple[bool, str]]:
        """The final answers of the requests made through `outcome()` so far, in request order."""
        return [o.result for o in self.outcomes if o.result is not None]

    def feed(self, st: VehicleState, dt: float = 0.02) -> None:
        self.t += dt
        self.mgr.on_vehicle(st, self.t)

    def tick(self, dt: float = 0.5, healthy: bool | None = None, fresh_state: bool = True) -> None:
        """Advance the clock; the vehicle state keeps arriving (as at 50 Hz) unless fresh_state=False."""
        self.t += dt
        if fresh_state and self.mgr.vehicle is not None:
            self.mgr.on_vehicle(self.mgr.vehicle, self.t)
        if healthy is not None:
            self.mgr.on_perception(healthy, self.t)
        self.mgr.tick(self.t)

    def silence(self, seconds: float, step: float = 0.1) -> None:
        """No state/vehicle for `seconds` while this service ticks on time (fmu silent)."""
        for _ in range(round(seconds / step)):
            self.tick(step, fresh_state=False)

    def clear(self) -> None:
        self.bridge.calls.clear()
        self.goals.clear()
        self.outcomes.clear()

    # ---- drive the manager into a state through its real inputs

    def to_idle(self, mission: Mission | None = None) -> None:
        self.feed(vehicle())
        ok, msg = self.mgr.load(mission or survey())
        assert ok, msg
        assert self.mgr.state == State.IDLE

    def to_takeoff(self, mission: Mission | None = None) -> None:
        self.to_idle(mission)
        ok, msg = self.mgr.command("TAKEOFF", self.outcome())
        assert ok, msg
        self.feed(vehicle(z=0.5, armed=True, landed=LandedState.IN_AIR))
        assert self.mgr.state == State.TAKEOFF

    def to_holding(self, mission: Mission | None = None) -> None:
        self.to_takeoff(mission)
        self.feed(flying(z=5.0))
        assert self.mgr.state == State.HOLDING

    def to_executing(self, mission: Mission | None = None) -> None:
        self.to_holding(mission)
        ok, msg = self.mgr.command("START", self.outcome())
        assert ok, msg
        assert self.mgr.state == State.EXECUTING

    def to_land(self, mission: Mission | None = None) -> None:
        self.to_executing(mission)
        ok, msg = self.mgr.command("LAND", self.outcome())
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



def fc(x=0.0, y=0.0, z=5.0, mode="OFFBOARD", armed=True, landed=LandedState.IN_AIR):
    return VehicleState(position_m=Vector3(x=x, y=y, z=z), armed=armed, landed_state=landed,
                        connected=True, flight_mode=mode)


def restarted(snapshot: dict | None, config: Config | None = None) -> Rig:
    """A fresh manager as a restarted service builds it: restore(snapshot), no vehicle state yet."""
    rig = Rig(config)
    rig.mgr.restore(snapshot, rig.t)
    return rig


def snapshot_mid_survey(wp_index: int = 2, state: str = "EXECUTING") -> dict:
    return {"mission_json": survey().to_json(), "wp_index": wp_index, "state": state, "start_requested": False}
