"""`aero eval trajectory --live`: how a flight followed its mission's legs, by the simulator's truth.

Figures (from the first waypoint reached to the last): flight time; cross-track error RMS / max
(distance from the straight legs between the waypoints; also horizontally only, since a flight
controller's height estimate may sit tenths of a metre off the truth: PX4 SIH's EKF2 0.2-0.8 m); peak speed, horizontal and vertical
acceleration and jerk (differences of the truth velocity over DIFF_WINDOW_S, so sensor-rate noise
does not pass for jerk); overshoot at each corner (how far outside the turn the vehicle went within
CORNER_RADIUS_M of it, horizontally: a height estimate's offset is no swing); and, when the planner flew a trajectory, its tracking error against its
own reference (planner/status position_error_m).
"""
from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field

import numpy as np

DIFF_WINDOW_S = 0.2
CORNER_RADIUS_M = 3.0


def distances_to_polyline(points: np.ndarray, legs: np.ndarray) -> np.ndarray:
    """Each point's distance to the nearest point of the polyline `legs` (n x 3)."""
    best = np.full(len(points), np.inf)
    for a, b in zip(legs, legs[1:]):
        ab = b - a
        n2 = float(np.dot(ab, ab))
        u = np.zeros(len(points)) if n2 < 1e-12 else np.clip((points - a) @ ab / n2, 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(a + u[:, None] * ab - points, axis=1))
    return best


def _derivative(ts: np.ndarray, values: np.ndarray, window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Central differences over about `window_s` (times at the middles)."""
    if len(ts) < 3:
        return ts[:0], values[:0]
    step = max(1, int(round(window_s / max(1e-6, float(np.median(np.diff(ts)))))))
    if len(ts) <= step:
        return ts[:0], values[:0]
    dt = ts[step:] - ts[:-step]
    ok = dt > 1e-6
    d = (values[step:] - values[:-step])[ok] / dt[ok, None]
    return ((ts[step:] + ts[:-step]) / 2)[ok], d


@dataclass
class TrajectoryEval:
    waypoints_m: np.ndarray                                  # the mission's waypoints (n x 3)
    truth: list[tuple[float, np.ndarray, np.ndarray, float]] = field(default_factory=list)  # (t, p, v, stamp)
    reached: dict[int, float] = field(default_factory=dict)  # waypoint index -> time first reached
    reference_errors: list[float] = field(default_factory=list)

    def add_truth(self, t_s: float, position_m: np.ndarray, velocity_mps: np.ndarray,
                  stamp_s: float | None = None) -> None:
        """`t_s` on the clock of the waypoint events (arrival time); `stamp_s` the sample's own
        stamp, for the differences (arrival times bunch up when a loaded host delivers late)."""
        self.truth.append((t_s, np.asarray(position_m, float), np.asarray(velocity_mps, float),
                           t_s if stamp_s is None else stamp_s))

    def add_reached(self, index: int, t_s: float) -> None:
        self.reached.setdefault(index, t_s)

    def add_reference_error(self, error_m: float) -> None:
        self.reference_errors.append(float(error_m))

    def summary(self) -> dict:
        n = len(self.waypoints_m)
        if 0 not in self.reached or n - 1 not in self.reached:
            missing = [i for i in (0, n - 1) if i not in self.reached]
            raise ValueError(f"waypoint(s) {missing} never reached: no complete flight to score")
        t0, t1 = self.reached[0], self.reached[n - 1]
        rows = [r for r in self.truth if t0 <= r[0] <= t1]
        if len(rows) < 5:
            raise ValueError(f"{len(rows)} truth samples between the first and the last waypoint")
        stamps = np.array([r[3] for r in rows])
        pos = np.array([r[1] for r in rows])
        vel = np.array([r[2] for r in rows])
        cross = distances_to_polyline(pos, self.waypoints_m)
        flat = np.array([1.0, 1.0, 0.0])
        cross_xy = distances_to_polyline(pos * flat, self.waypoints_m * flat)
        ta, acc = _derivative(stamps, vel, DIFF_WINDOW_S)
        _, jerk = _derivative(ta, acc, DIFF_WINDOW_S)
        overshoot = []
        for k in range(1, n - 1):
            a, c, b = self.waypoints_m[k - 1], self.waypoints_m[k], self.waypoints_m[k + 1]
            # the outside of a left turn is right of either leg (wide before it, or past it); of a right turn, left
            turn = np.sign(np.cross(c - a, b - c)[2])
            near = np.linalg.norm(pos[:, :2] - c[:2], axis=1) < CORNER_RADIUS_M
            side_in = np.cross(np.broadcast_to(c - a, pos.shape), pos - a)[:, 2]
            side_out = np.cross(np.broadcast_to(b - c, pos.shape), pos - c)[:, 2]
            outside = near & ((turn * side_in < 0) | (turn * side_out < 0))
            overshoot.append(float(cross_xy[outside].max()) if outside.any() else 0.0)
        ref = np.array(self.reference_errors)
        return {
            "time_s": round(t1 - t0, 2),
            "cross_track_rms_m": round(float(np.sqrt(np.mean(cross ** 2))), 3),
            "cross_track_max_m": round(float(cross.max()), 3),
            "cross_track_xy_rms_m": round(float(np.sqrt(np.mean(cross_xy ** 2))), 3),
            "cross_track_xy_max_m": round(float(cross_xy.max()), 3),
            "peak_speed_mps": round(float(np.linalg.norm(vel, axis=1).max()), 3),
            "peak_xy_speed_mps": round(float(np.hypot(vel[:, 0], vel[:, 1]).max()), 3),
            "peak_xy_acc_mps2": round(float(np.hypot(acc[:, 0], acc[:, 1]).max()) if len(acc) else 0.0, 3),
            "peak_z_acc_mps2": round(float(np.abs(acc[:, 2]).max()) if len(acc) else 0.0, 3),
            "peak_jerk_mps3": round(float(np.linalg.norm(jerk, axis=1).max()) if len(jerk) else 0.0, 3),
            "peak_xy_jerk_mps3": round(float(np.hypot(jerk[:, 0], jerk[:, 1]).max()) if len(jerk) else 0.0, 3),
            "corner_overshoot_m": [round(o, 3) for o in overshoot],
            "reference_error_rms_m": round(float(np.sqrt(np.mean(ref ** 2))), 3) if len(ref) else None,
            "reference_error_max_m": round(float(ref.max()), 3) if len(ref) else None,
            "truth_samples": len(rows),
        }


def table(res: dict) -> str:
    ref = ("-" if res["reference_error_rms_m"] is None
           else f"{res['reference_error_rms_m']:.3f} / {res['reference_error_max_m']:.3f} m")
    lines = [
        f"time (first to last waypoint)   {res['time_s']:.2f} s",
        f"cross-track RMS / max           {res['cross_track_rms_m']:.3f} / {res['cross_track_max_m']:.3f} m",
        f"  horizontal only               {res['cross_track_xy_rms_m']:.3f} / {res['cross_track_xy_max_m']:.3f} m",
        f"peak speed (xy)                 {res['peak_speed_mps']:.2f} ({res['peak_xy_speed_mps']:.2f}) m/s",
        f"peak acceleration xy / z        {res['peak_xy_acc_mps2']:.2f} / {res['peak_z_acc_mps2']:.2f} m/s^2",
        f"peak jerk (xy)                  {res['peak_jerk_mps3']:.2f} ({res['peak_xy_jerk_mps3']:.2f}) m/s^3",
        f"corner overshoot                {', '.join(f'{o:.2f}' for o in res['corner_overshoot_m']) or '-'} m",
        f"tracking vs reference RMS / max {ref}",
    ]
    return "\n".join(lines)


def run_live(args) -> int:
    from aeroperception.schemas import (
        Empty, GetMissionReply, MissionStatus, SchemaError, TrajectoryStatus, VehicleState, WaypointReached, decode, parse_mission,
    )
    from aeroperception.services.runtime.node import call

    from aeroperception.tools.common import CliError, FlightWatch, open_client

    prefix = f"{args.vehicle}/" if args.vehicle else ""
    session = open_client(args)
    lock, watch, subs = threading.Lock(), FlightWatch(), []
    try:
        ev = TrajectoryEval(np.zeros((0, 3)))    # the waypoints: the mission's once it flies
        flying = threading.Event()

        def on_mission_status(sample) -> None:
            try:
                m = decode(sample.payload.to_bytes(), MissionStatus)
            except SchemaError:
                return
            if m.state != MissionStatus.STATE_IDLE:
                flying.set()

        def on_truth(sample) -> None:
            try:
                m = decode(sample.payload.to_bytes(), VehicleState)
            except SchemaError:
                return
            watch.update(m.armed, m.position_m.z)
            with lock:
                ev.add_truth(time.monotonic(), m.position_m.to_array(), m.velocity_mps.to_array(),
                             m.header.stamp_ns * 1e-9)

        def on_reached(sample) -> None:
            try:
                m = decode(sample.payload.to_bytes(), WaypointReached)
            except SchemaError:
                return
            with lock:
                ev.add_reached(m.index, time.monotonic())

        def on_status(sample) -> None:
            try:
                m = decode(sample.payload.to_bytes(), TrajectoryStatus)
            except SchemaError:
                return
            if m.status == TrajectoryStatus.STATUS_EXECUTING and not m.trajectory_id.startswith("goal-"):
                with lock:
                    ev.add_reference_error(m.position_error_m)

        subs = [session.declare_subscriber(prefix + "sim/truth/state", on_truth),
                session.declare_subscriber(prefix + "mission/waypoint_reached", on_reached),
                session.declare_subscriber(prefix + "planner/status", on_status),
                session.declare_subscriber(prefix + "mission/status", on_mission_status)]
        end_s = time.monotonic() + args.duration
        # Started before `aero mission fly FILE` (which loads it): the mission scored is the one
        # loaded once the mission leaves IDLE, not one a previous flight left loaded.
        if not flying.is_set():
            print("waiting for a mission to fly (aero mission fly FILE) ...", flush=True)
        if not flying.wait(args.duration):
            raise CliError(f"no mission flew within {args.duration:g} s (mission/status stayed IDLE): "
                           "start one (aero mission fly FILE)")
        try:
            reply = call(session, prefix + "mission/srv/get", Empty(), GetMissionReply, 5.0)
        except Exception as e:  # noqa: BLE001 - no mission service: one line
            raise CliError(f"mission/srv/get: {e} (is the stack up: aero up?)") from None
        if not reply.success:
            raise CliError("no mission loaded (mission/srv/get) although the mission left IDLE")
        with lock:
            ev.waypoints_m = np.array([[w.x, w.y, w.z] for w in parse_mission(reply.mission_json).waypoints], float)
        print(f"scoring the flight of {len(ev.waypoints_m)} waypoints for {args.duration:g} s"
              + (" at most, until the vehicle has flown and landed" if args.until_landed else "") + " ...", flush=True)
        watch.wait(max(0.0, end_s - time.monotonic()), args.until_landed)
    finally:
        for s in subs:
            s.undeclare()
        session.close()
    with lock:
        try:
            res = ev.summary()
        except ValueError as e:
            raise CliError(f"{e} (is the stack flying the mission: aero mission fly?)") from None
    print(table(res))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=2)
    return 0
