"""`aero mcap export --foxglove`: a second MCAP with JSON messages in Foxglove's well-known
schemas, so Foxglove's 3D, Image, Plot and Log panels understand it without our schemas.

Mapping (ENU stays ENU: Foxglove's frames are right-handed like ours):
  VehicleState, Odometry, PoseStamped, MissionGoal -> foxglove.PoseInFrame (+ foxglove.FrameTransform
  `<key>/tf` map->base_link for VehicleState, so the 3D panel can follow the vehicle);
  Image -> foxglove.RawImage; PointCloud -> foxglove.PointCloud (x, y, z float32 [+ intensity]);
  OccupancyGrid -> foxglove.Grid (int8 cost); DiagnosticStatus/Array -> foxglove.Log (one per
  status); anything else -> its own fields as JSON under our schema name and JSON Schema.

The JSON Schemas written into the file are generated from Foxglove's published definitions
(PyPI foxglove-schemas-protobuf): every field required, as in Foxglove's own JSON schemas.
"""
from __future__ import annotations

import base64
import json
from typing import Any, Callable, Iterator

import msgspec

from aeroperception.schemas import REGISTRY, DiagnosticStatus, SchemaError, decode

from .files import messages
from .logic import json_schema

# ---------------------------------------------------------------- Foxglove schemas

NUMERIC = {"uint8": 1, "int8": 2, "uint16": 3, "int16": 4, "uint32": 5, "int32": 6, "float32": 7, "float64": 8}
LOG_LEVEL = {DiagnosticStatus.OK: 2, DiagnosticStatus.WARN: 3, DiagnosticStatus.ERROR: 4, DiagnosticStatus.STALE: 3}


def foxglove_json_schema(name: str) -> dict:
    """The JSON Schema of foxglove.<name> from its protobuf definition (proto3 JSON of Foxglove's
    JSON encoding: snake_case names, time as {sec, nsec}, bytes as base64, enums as integers)."""
    import importlib

    mod = importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2")
    doc = _message_schema(getattr(mod, name).DESCRIPTOR)
    doc["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    return doc


def _message_schema(d) -> dict:
    from google.protobuf.descriptor import FieldDescriptor as F

    if d.full_name == "google.protobuf.Timestamp" or d.full_name == "google.protobuf.Duration":
        return {"type": "object", "title": "time",
                "properties": {"sec": {"type": "integer", "minimum": 0},
                               "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
                "required": ["sec", "nsec"]}
    props, required = {}, []
    for f in d.fields:
        if f.type == F.TYPE_MESSAGE:
            t = _message_schema(f.message_type)
        elif f.type == F.TYPE_ENUM:
            t = {"type": "integer", "enum": [v.number for v in f.enum_type.values]}
        elif f.type == F.TYPE_BYTES:
            t = {"type": "string", "contentEncoding": "base64"}
        elif f.type == F.TYPE_STRING:
            t = {"type": "string"}
        elif f.type == F.TYPE_BOOL:
            t = {"type": "boolean"}
        elif f.type in (F.TYPE_DOUBLE, F.TYPE_FLOAT):
            t = {"type": "number"}
        else:
            t = {"type": "integer"}
            if f.type in (F.TYPE_UINT32, F.TYPE_FIXED32, F.TYPE_UINT64, F.TYPE_FIXED64):
                t["minimum"] = 0
        props[f.name] = {"type": "array", "items": t} if f.is_repeated else t
        if f.is_repeated or f.type == F.TYPE_MESSAGE or not f.has_presence:
            required.append(f.name)   # proto3 `optional` scalars are the only optional fields
    return {"title": d.full_name, "type": "object", "properties": props, "required": required}


# ---------------------------------------------------------------- conversions


def _time(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _b64(data) -> str:
    return base64.b64encode(bytes(data)).decode()


def _vec(v) -> dict:
    return {"x": v.x, "y": v.y, "z": v.z}


def _quat(q) -> dict:
    return {"x": q.x, "y": q.y, "z": q.z, "w": q.w}


def _pose(p) -> dict:
    return {"position": _vec(p.position), "orientation": _quat(p.orientation)}


def _pose_in_frame(stamp: int, frame: str, pose: dict) -> dict:
    return {"timestamp": _time(stamp), "frame_id": frame, "pose": pose}


def _vehicle_state(key: str, m) -> Iterator[tuple[str, str, dict]]:
    pose = {"position": _vec(m.position_m), "orientation": _quat(m.orientation)}
    yield key, "PoseInFrame", _pose_in_frame(m.header.stamp_ns, m.header.frame_id or "map", pose)
    yield f"{key}/tf", "FrameTransform", {
        "timestamp": _time(m.header.stamp_ns), "parent_frame_id": m.header.frame_id or "map",
        "child_frame_id": "base_link", "translation": pose["position"], "rotation": pose["orientation"]}


def _odometry(key: str, m):
    yield key, "PoseInFrame", _pose_in_frame(m.header.stamp_ns, m.header.frame_id or "odom", _pose(m.pose))


def _pose_stamped(key: str, m):
    yield key, "PoseInFrame", _pose_in_frame(m.header.stamp_ns, m.header.frame_id or "map", _pose(m.pose))


def _image(key: str, m):
    yield key, "RawImage", {"timestamp": _time(m.header.stamp_ns), "frame_id": m.header.frame_id,
                            "width": m.width, "height": m.height, "encoding": m.encoding,
                            "step": m.step, "data": _b64(m.data.data)}


def _identity() -> dict:
    return {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def _point_cloud(key: str, m):
    import numpy as np

    pts = m.points.to_numpy().astype("<f4")
    fields = [{"name": n, "offset": 4 * i, "type": NUMERIC["float32"]} for i, n in enumerate("xyz")]
    cols = [pts]
    if m.intensity is not None:
        fields.append({"name": "intensity", "offset": 12, "type": NUMERIC["float32"]})
        cols.append(m.intensity.to_numpy().astype("<f4").reshape(-1, 1))
    packed = np.ascontiguousarray(np.hstack(cols)) if len(cols) > 1 else np.ascontiguousarray(pts)
    yield key, "PointCloud", {"timestamp": _time(m.header.stamp_ns), "frame_id": m.header.frame_id,
                              "pose": _identity(), "point_stride": 4 * len(fields), "fields": fields,
                              "data": _b64(packed.tobytes())}


def _grid(key: str, m):
    yield key, "Grid", {"timestamp": _time(m.header.stamp_ns), "frame_id": m.header.frame_id or "map",
                        "pose": _pose(m.origin), "column_count": m.width,
                        "cell_size": {"x": m.resolution_m, "y": m.resolution_m},
                        "row_stride": m.width, "cell_stride": 1,
                        "fields": [{"name": "cost", "offset": 0, "type": NUMERIC["int8"]}],
                        "data": _b64(m.data.data)}


def _log(st, stamp: int) -> dict:
    return {"timestamp": _time(stamp), "level": LOG_LEVEL.get(st.level, 0),
            "message": st.message, "name": st.name, "file": "", "line": 0}


def _diag(key: str, m):
    yield key, "Log", _log(m, m.header.stamp_ns)


def _diag_array(key: str, m):
    for st in m.status:
        yield key, "Log", _log(st, m.header.stamp_ns)


CONVERTERS: dict[str, Callable[[str, Any], Iterator[tuple[str, str, dict]]]] = {
    "VehicleState": _vehicle_state, "Odometry": _odometry, "PoseStamped": _pose_stamped,
    "MissionGoal": _pose_stamped, "Image": _image,
    "PointCloud": _point_cloud, "OccupancyGrid": _grid, "DiagnosticStatus": _diag, "DiagnosticArray": _diag_array,
}


def convert(key: str, schema_id: str, payload: bytes) -> Iterator[tuple[str, str, bytes]]:
    """(topic, schema name, JSON bytes) for one recorded message; nothing if it does not decode.
    Schema names are "foxglove.X" for the well-known ones, else our "<name>@<version>"."""
    name = schema_id.partition("@")[0]
    cls = REGISTRY.get(name)
    if cls is None:
        return
    try:
        msg = decode(payload, cls)
    except SchemaError:
        return
    conv = CONVERTERS.get(name)
    if conv is None:
        yield key, schema_id, msgspec.json.encode(msg)   # bytes -> base64, as msgspec's JSON Schema says
        return
    for topic, fox, obj in conv(key, msg):
        yield topic, f"foxglove.{fox}", json.dumps(obj).encode()


def export(src: str, dst: str) -> dict[str, int]:
    """Write `dst`: every message of `src` converted (see module doc). Returns counts per topic."""
    from mcap.writer import CompressionType, Writer

    counts: dict[str, int] = {}
    schemas: dict[str, int] = {}
    channels: dict[tuple[str, str], int] = {}
    with open(dst, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="aero mcap export")
        for ch, m in messages(src):
            for topic, sname, data in convert(ch.topic, ch.metadata.get("schema", ""), m.data):
                cid = channels.get((topic, sname))
                if cid is None:
                    sid = schemas.get(sname)
                    if sid is None:
                        doc = (json.dumps(foxglove_json_schema(sname.removeprefix("foxglove."))).encode()
                               if sname.startswith("foxglove.") else json_schema(sname))
                        sid = schemas[sname] = w.register_schema(sname, "jsonschema", doc)
                    cid = channels[(topic, sname)] = w.register_channel(topic, "json", sid)
                w.add_message(cid, log_time=m.log_time, publish_time=m.publish_time, data=data)
                counts[topic] = counts.get(topic, 0) + 1
        w.finish()
    return counts
