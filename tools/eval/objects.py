"""`aero eval objects --live | --replay FILE`: the objects service's tracks against the simulator's truth.

Truth is the scenario's detector targets (their 3D box centres, ENU): the running sim's scenario,
named with --scenario. --live scores the running service; --replay runs the service's own pipeline
(`ObjectsPipeline`, no Zenoh) over a recorded flight (an MCAP with the detections, the stereo pair,
camera infos, vehicle state and home: `aero record --images`), every detection frame in stamp
order, so a change to the objects logic is judged on the same flight again. Every
perception/objects message is scored as it comes:
- each confirmed track is matched to the nearest target of its class within `match_m`; a target
  with one track is found, each further track on it is a duplicate, a target with none is missed;
- a confirmed track near no target of its class is a false track (reported with how long it lived);
- position error: every sample of a matched confirmed track at a range inside `range_m`, also by
  range band (`BANDS_M`);
- ID switches: a target whose matched track id changes from one message to the next;
- time to confirmation: a track's first confirmed message minus its first detection;
- the service's cost per detection frame and its frames dropped while busy (diagnostics/objects;
  on a replay: this process's CPU per frame, and nothing is dropped).
"""
from __future__ import annotations

import json
import threading
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from aeroperception.schemas import TrackedObjectArray

MATCH_M = 3.0
# The search flight's goals: every target found exactly once, position error at 5-30 m (median, p95),
# no false track living longer than this, the service's CPU per detection frame (p99).
GOALS = {"error_median_m": 0.5, "error_p95_m": 1.5, "false_track_life_s": 2.0, "frame_cpu_ms_p99": 5.0}
BANDS_M = ((5.0, 10.0), (10.0, 20.0), (20.0, 30.0))


@dataclass(frozen=True)
class Target:
    index: int
    class_name: str
    center_m: np.ndarray


def scenario_targets(scenario: str) -> list[Target]:
    from aeroperception.services.sim.world.scenario import load_scenario
    from aeroperception.services.sim.world.scene import get_scene

    return [Target(b.target_index, b.class_name, np.asarray(b.center_enu_m, float))
            for b in get_scene(load_scenario(scenario)).target_boxes]


@dataclass
class ObjectsEval:
    targets: list[Target]
    match_m: float = MATCH_M
    range_m: tuple[float, float] = (5.0, 30.0)
    errors: dict[str, list[tuple[float, float]]] = field(default_factory=lambda: defaultdict(list))   # (range, error)
    tracks_on: dict[int, set[int]] = field(default_factory=lambda: defaultdict(set))     # target -> track ids
    false_tracks: dict[int, tuple[str, float]] = field(default_factory=dict)             # id -> (class, lifetime s)
    last_id: dict[int, int] = field(default_factory=dict)                                # target -> track id
    id_switches: int = 0
    confirm_s: dict[int, float] = field(default_factory=dict)                            # track id -> s
    messages: int = 0
    service: dict[str, float] = field(default_factory=dict)                              # diagnostics/objects

    def match(self, class_name: str, position: np.ndarray) -> Target | None:
        best, best_d = None, self.match_m
        for t in self.targets:
            if t.class_name == class_name:
                d = float(np.linalg.norm(t.center_m - position))
                if d <= best_d:
                    best, best_d = t, d
        return best

    def add(self, msg: TrackedObjectArray) -> None:
        self.messages += 1
        nearest: dict[int, tuple[float, int]] = {}
        for o in msg.objects:
            if not o.confirmed:
                continue
            p = o.position_m.to_array()
            self.confirm_s.setdefault(o.track_id, (o.last_seen_ns - o.first_seen_ns) * 1e-9)
            t = self.match(o.class_name, p)
            if t is None:
                self.false_tracks[o.track_id] = (o.class_name, (o.last_seen_ns - o.first_seen_ns) * 1e-9)
                continue
            self.false_tracks.pop(o.track_id, None)
            self.tracks_on[t.index].add(o.track_id)
            err = float(np.linalg.norm(t.center_m - p))
            if self.range_m[0] <= o.range_m <= self.range_m[1]:
                self.errors[t.class_name].append((o.range_m, err))
            if t.index not in nearest or err < nearest[t.index][0]:
                nearest[t.index] = (err, o.track_id)
        for index, (_, track_id) in nearest.items():
            if index in self.last_id and self.last_id[index] != track_id:
                self.id_switches += 1
            self.last_id[index] = track_id

    def add_diagnostics(self, values: dict[str, str]) -> None:
        """The objects service's own counters: the newest frame counts and per-frame costs, and the
        worst per-frame maximum seen over the run."""
        for k in ("frames_received", "frames_processed", "frames_dropped_busy", "frame_ms_p50", "frame_cpu_ms_p50",
                  "frame_cpu_ms_p99"):
            if k in values:
                self.service[k] = float(values[k])
        for k in ("frame_ms_max", "frame_cpu_ms_max"):
            if k in values:
                self.service[k] = max(self.service.get(k, 0.0), float(values[k]))

    def _false(self, cls: str) -> dict:
        lives = sorted(life for c, life in self.false_tracks.values() if c == cls)
        return {"false_tracks": len(lives), "false_tracks_over_2s": sum(life > GOALS["false_track_life_s"] for life in lives),
                "false_track_lifetimes_s": [round(life, 1) for life in lives]}

    def summary(self) -> dict:
        per_class: dict[str, dict] = {}
        for cls in sorted({t.class_name for t in self.targets}):
            mine = [t for t in self.targets if t.class_name == cls]
            samples = np.asarray(self.errors.get(cls, []), float).reshape(-1, 2)
            errs = samples[:, 1]
            per_class[cls] = {
                "targets": len(mine),
                "found": sum(1 for t in mine if self.tracks_on.get(t.index)),
                "missed": sum(1 for t in mine if not self.tracks_on.get(t.index)),
                "duplicates": sum(max(0, len(self.tracks_on.get(t.index, ())) - 1) for t in mine),
                **self._false(cls),
                "error_median_m": round(float(np.median(errs)), 3) if errs.size else None,
                "error_p95_m": round(float(np.percentile(errs, 95)), 3) if errs.size else None,
                "error_samples": int(errs.size),
                "bands": {f"{lo:g}-{hi:g}": _quantiles(errs[(samples[:, 0] >= lo) & (samples[:, 0] < hi)])
                          for lo, hi in BANDS_M},
            }
        for cls in sorted({c for c, _ in self.false_tracks.values()} - set(per_class)):
            per_class[cls] = {"targets": 0, "found": 0, "missed": 0, "duplicates": 0, **self._false(cls),
                              "error_median_m": None, "error_p95_m": None, "error_samples": 0, "bands": {}}
        delays = list(self.confirm_s.values())
        return {"classes": per_class, "id_switches": self.id_switches, "messages": self.messages,
                "confirm_s_median": round(float(np.median(delays)), 2) if delays else None,
                "confirm_s_max": round(float(max(delays)), 2) if delays else None, "service": dict(self.service)}


def unmet_goals(res: dict) -> list[str]:
    """The goals `res` (a summary) misses, one line each; empty when all are met."""
    out = []
    for cls, r in res["classes"].items():
        if r["missed"]:
            out.append(f"{cls}: {r['missed']} of {r['targets']} targets missed")
        if r["duplicates"]:
            out.append(f"{cls}: {r['duplicates']} duplicate tracks")
        if r["false_tracks_over_2s"]:
            out.append(f"{cls}: {r['false_tracks_over_2s']} false tracks living > {GOALS['false_track_life_s']:g} s "
                       f"({r['false_track_lifetimes_s']} s)")
        for k in ("error_median_m", "error_p95_m"):
            if r[k] is not None and r[k] >= GOALS[k]:
                out.append(f"{cls}: position error {k[6:-2]} {r[k]:.2f} m (goal < {GOALS[k]:g} m)")
    cpu = (res.get("service") or {}).get("frame_cpu_ms_p99")
    if cpu is not None and cpu >= GOALS["frame_cpu_ms_p99"]:
        out.append(f"objects service: CPU p99 {cpu:.2f} ms per frame (goal < {GOALS['frame_cpu_ms_p99']:g} ms)")
    return out


def _quantiles(errs: np.ndarray) -> dict:
    return {"median_m": round(float(np.median(errs)), 3) if errs.size else None,
            "p95_m": round(float(np.percentile(errs, 95)), 3) if errs.size else None, "samples": int(errs.size)}


def table(res: dict) -> str:
    rows = [f"{'class':<10} {'targets':>7} {'found':>5} {'missed':>6} {'dup':>3} {'false':>5} {'>2s':>3} "
            f"{'err p50 m':>9} {'p95 m':>6} {'n':>5}"]
    for cls, r in res["classes"].items():
        rows.append(f"{cls:<10} {r['targets']:>7} {r['found']:>5} {r['missed']:>6} {r['duplicates']:>3} "
                    f"{r['false_tracks']:>5} {r['false_tracks_over_2s']:>3} {_fmt(r['error_median_m']):>9} "
                    f"{_fmt(r['error_p95_m']):>6} {r['error_samples']:>5}")
    rows.append("error by range (median / p95 m, samples): " + "; ".join(
        f"{cls} " + ", ".join(f"{band} {_fmt(q['median_m'])}/{_fmt(q['p95_m'])} ({q['samples']})" for band, q in r["bands"].items())
        for cls, r in res["classes"].items() if r["bands"]))
    lives = {cls: r["false_track_lifetimes_s"] for cls, r in res["classes"].items() if r["false_track_lifetimes_s"]}
    if lives:
        rows.append("false tracks' lifetimes (s): " + "; ".join(f"{cls} {v}" for cls, v in lives.items()))
    rows.append(f"ID switches {res['id_switches']}; time to confirmation median {res['confirm_s_median']} s, "
                f"max {res['confirm_s_max']} s; {res['messages']} perception/objects messages")
    sv = res.get("service") or {}
    if sv:
        rows.append(f"objects service per frame: CPU p50 {sv.get('frame_cpu_ms_p50')} ms, p99 {sv.get('frame_cpu_ms_p99')} "
                    f"ms, max {sv.get('frame_cpu_ms_max')} ms; wall p50 {sv.get('frame_ms_p50')} ms, max "
                    f"{sv.get('frame_ms_max')} ms; frames {sv.get('frames_received', 0):.0f} received, "
                    f"{sv.get('frames_processed', 0):.0f} processed, {sv.get('frames_dropped_busy', 0):.0f} dropped busy")
    return "\n".join(rows)


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def report(res: dict, json_path: str | None) -> int:
    """Print the table and the unmet goals; keep the figures as JSON when asked."""
    print(table(res))
    unmet = unmet_goals(res)
    print("goals: met" if not unmet else "goals not met: " + "; ".join(unmet))
    res["unmet_goals"] = unmet
    if json_path:
        with open(json_path, "w") as f:
            json.dump(res, f, indent=2)
    return 0


def run_live(args) -> int:
    from aeroperception.schemas import DiagnosticStatus, SchemaError, decode

    from aeroperception.tools.common import CliError, FlightWatch, open_client

    ev = ObjectsEval(_targets(args.scenario or "village"))
    prefix = f"{args.vehicle}/" if args.vehicle else ""
    lock, watch = threading.Lock(), FlightWatch()

    def on_objects(sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), TrackedObjectArray)
        except SchemaError:
            return
        with lock:
            ev.add(msg)

    def on_diagnostics(sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), DiagnosticStatus)
        except SchemaError:
            return
        with lock:
            ev.add_diagnostics(dict(msg.values))

    session = open_client(args)
    subs = []
    try:
        subs = [session.declare_subscriber(prefix + "perception/objects", on_objects),
                session.declare_subscriber(prefix + "sim/truth/state", watch.on_sample),
                session.declare_subscriber(prefix + "diagnostics/objects", on_diagnostics)]
        print(f"scoring perception/objects against {args.scenario}'s {len(ev.targets)} targets for "
              f"{args.duration:g} s" + (" at most, until the vehicle has flown and landed" if args.until_landed else "")
              + " ...", flush=True)
        watch.wait(args.duration, args.until_landed)
    finally:
        for s in subs:
            s.undeclare()
        session.close()
    with lock:
        if ev.messages == 0:
            raise CliError("no perception/objects message: is the objects service running (aero up)?")
        res = ev.summary()
    return report(res, args.json)


def _targets(scenario: str) -> list[Target]:
    from aeroperception.tools.common import CliError

    try:
        return scenario_targets(scenario)
    except Exception as e:  # noqa: BLE001 - a bad scenario name or file: one line
        raise CliError(f"--scenario {scenario}: {e}") from None


# ---------------------------------------------------------------- replay

REPLAY_INPUTS = ("perception/detections", "state/vehicle", "fmu/out/home_position", "sensors/camera/left/info",
                 "sensors/camera/right/info", "sensors/camera/left/image", "sensors/camera/right/image")


@dataclass
class Replay:
    """The objects pipeline fed a recording's messages in log-time order, scored as it goes."""

    pipeline: object                    # services.objects.logic.ObjectsPipeline
    eval: ObjectsEval
    cpu_ms: list[float] = field(default_factory=list)
    wall_ms: list[float] = field(default_factory=list)
    frames: int = 0
    undecodable: int = 0

    def feed(self, key: str, payload: bytes) -> None:
        from aeroperception.schemas import (
            CameraInfo, Detection2DArray, HomePosition, Image, SchemaError, VehicleState, decode,
        )

        topic, pl = key.split("/"), self.pipeline
        kind = {"state/vehicle": VehicleState, "fmu/out/home_position": HomePosition,
                "perception/detections": Detection2DArray}.get(key) or (CameraInfo if topic[-1] == "info" else Image)
        try:
            msg = decode(payload, kind)
        except SchemaError:
            self.undecodable += 1
            return
        if kind is VehicleState:
            pl.on_state(msg)
        elif kind is HomePosition:
            pl.on_home(msg)
        elif kind is CameraInfo:
            pl.on_info(topic[2], msg)
        elif kind is Image:
            pl.on_image(topic[2], msg)
        else:
            self.frames += 1
            r = pl.process(msg)
            if r is not None:
                self.cpu_ms.append(r.cpu_ms)
                self.wall_ms.append(r.elapsed_ms)
                self.eval.add(r.objects)

    def summary(self) -> dict:
        cpu, wall = np.asarray(self.cpu_ms, float), np.asarray(self.wall_ms, float)
        if cpu.size:
            self.eval.service.update(frames_received=self.frames, frames_processed=cpu.size, frames_dropped_busy=0,
                                     frame_ms_p50=round(float(np.median(wall)), 2), frame_ms_max=round(float(wall.max()), 2),
                                     frame_cpu_ms_p50=round(float(np.median(cpu)), 2),
                                     frame_cpu_ms_p99=round(float(np.percentile(cpu, 99)), 2),
                                     frame_cpu_ms_max=round(float(cpu.max()), 2))
        res = self.eval.summary()
        res["replay"] = {"detection_frames": self.frames, "undecodable": self.undecodable,
                         "dropped": dict(self.pipeline.dropped), "placed": dict(self.pipeline.placed)}
        return res


def replay(path: str, scenario: str | None = None, overrides: dict[str, str] | None = None,
           vehicle: str = "") -> dict:
    """Score the objects logic on a recorded flight (module doc). `scenario`: the truth's, else the
    one the recording names; `overrides`: objects parameters (NAME -> value) instead of defaults."""
    from aeroperception.services.objects import contract
    from aeroperception.services.objects.logic import ObjectsConfig, ObjectsPipeline
    from aeroperception.services.recorder.files import RecordingError, messages
    from aeroperception.services.runtime import ParamError, ParamSet
    from aeroperception.services.runtime.config import build
    from aeroperception.tools.common import CliError

    recorded, metadata = _recorded(path)
    scenario = scenario or metadata.get("aeroperception", {}).get("scenario")
    if not scenario:
        raise CliError(f"{path} does not name its scenario: give --scenario (e.g. village)")
    prefix = f"{vehicle}/" if vehicle else ""
    topics = [prefix + k for k in REPLAY_INPUTS]
    missing = [k for k in ("perception/detections", "state/vehicle", "sensors/camera/left/info")
               if prefix + k not in recorded]
    if missing:
        raise CliError(f"{path} has no {', '.join(missing)}: record them (aero record --images "
                       f"{' '.join(REPLAY_INPUTS[:5])})")
    params = ParamSet.from_declarations(contract.PARAMS)
    try:
        params.update(overrides or {})
    except ParamError as e:
        raise CliError(f"--param: {e}") from None
    run = Replay(ObjectsPipeline(build(ObjectsConfig, params)), ObjectsEval(_targets(scenario)))
    try:
        for ch, m in messages(path, topics):
            run.feed(ch.topic[len(prefix):], m.data)
    except RecordingError as e:
        raise CliError(str(e)) from None
    if not run.cpu_ms:
        raise CliError(f"{path}: no detection frame could be placed ({dict(run.pipeline.dropped)})")
    res = run.summary()
    res["replay"]["file"], res["replay"]["scenario"] = str(path), scenario
    return res


def _recorded(path: str) -> tuple[set[str], dict[str, dict[str, str]]]:
    """The topics and metadata of an indexed recording, from its summary (not a pass over its images)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    from aeroperception.tools.common import CliError

    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is None:
                raise CliError(f"{path}: has no index (cut short?): run `aero mcap recover {path}` first")
            return ({c.topic for c in summary.channels.values()},
                    {m.name: dict(m.metadata) for m in reader.iter_metadata()})
    except (OSError, McapError) as e:
        raise CliError(f"{path}: not a readable MCAP recording ({e})") from None


def run_replay(args) -> int:
    from aeroperception.services.runtime import ParamError
    from aeroperception.services.runtime.params import parse_overrides
    from aeroperception.tools.common import CliError

    try:
        overrides = parse_overrides(args.param or ())
    except ParamError as e:
        raise CliError(str(e)) from None
    res = replay(args.replay, args.scenario, overrides, args.vehicle or "")
    r = res["replay"]
    print(f"replayed {r['file']} ({r['scenario']}): {r['detection_frames']} detection frames; placed {r['placed']}; "
          f"not placed {r['dropped']}")
    return report(res, args.json)
