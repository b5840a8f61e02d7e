"""Decoded arrays are aligned for their dtype wherever msgpack put them in the payload.

A decoded NDArray's bytes are a view into the received payload at whatever offset its field
landed on (it depends on the message's content: a longer frame_id shifts every array after it).
Native code that takes such arrays without copying requires aligned memory: Rerun's Arrow import
panicked and aborted the viewer on a float32 cloud at an odd address. Every array-carrying schema
is decoded here from payloads placed at each start offset 0..7, so each array lands on every
offset mod 8, and handed to every consumer that passes arrays to native code: viz (Rerun), the
ROS 2 bridge (CDR), the Foxglove export, lidar (the pipeline), vio (OpenCV front end) and the
detector (ONNX Runtime). A consumer runs in its own process: an abort fails the test, not the run.
"""
from __future__ import annotations

import multiprocessing
from types import SimpleNamespace

import msgspec
import msgspec.inspect as ti
import numpy as np
import pytest

from aeroperception.schemas import (
    REGISTRY, CameraInfo, Header, Image, Imu, NDArray, OccupancyGrid, Odometry, PointCloud, Pose, Quaternion,
    UAVStatus, Vector3, VehicleState, decode, encode, schema_id,
)

OFFSETS = range(8)


def _cov(n: int, seed: int) -> NDArray:
    a = np.random.default_rng(seed).normal(size=(n, n))
    return NDArray.from_numpy(a @ a.T)


def _state() -> VehicleState:
    return VehicleState(header=Header(stamp_ns=123, frame_id="map"), pose_covariance=_cov(6, 1),
                        twist_covariance=_cov(6, 2))


def stereo_info(y_m: float) -> CameraInfo:
    """One camera of a forward stereo pair, `y_m` left of the body's x axis."""
    from aeroperception.services.runtime.rotations import quat_from_rotmat
    from aeroperception.services.sim.sensors.frames import R_FLU_OPTICAL_FORWARD

    q = Quaternion.from_array(quat_from_rotmat(R_FLU_OPTICAL_FORWARD))
    return CameraInfo.pinhole(640, 480, 400.0, 400.0, 319.5, 239.5,
                              T_body_camera=Pose(position=Vector3(x=0.1, y=y_m, z=0.0), orientation=q))


def _texture(h: int = 480, w: int = 640) -> np.ndarray:
    rng = np.random.default_rng(3)
    small = rng.integers(0, 255, size=(h // 8, w // 8, 3), dtype=np.uint8)
    return np.ascontiguousarray(np.repeat(np.repeat(small, 8, axis=0), 8, axis=1))


def samples() -> dict[type, msgspec.Struct]:
    """A realistic message of every schema that carries arrays."""
    rng = np.random.default_rng(0)
    pts = rng.uniform(-20, 20, size=(4000, 3)).astype(np.float32)
    pts[:2000, 2] = rng.normal(-1.5, 0.02, 2000)                     # a ground for the lidar pipeline
    return {
        Image: Image.from_numpy(_texture(), "rgb8", Header(stamp_ns=5, frame_id="camera_left")),
        CameraInfo: stereo_info(0.05),
        PointCloud: PointCloud.from_numpy(pts, intensity=rng.random(4000), labels=rng.integers(0, 3, 4000),
                                          header=Header(stamp_ns=7, frame_id="map")),
        OccupancyGrid: OccupancyGrid(header=Header(frame_id="map"), resolution_m=0.2, width=50, height=40,
                                     data=NDArray.from_numpy(rng.integers(-1, 100, size=(40, 50)), "int8")),
        Imu: Imu(header=Header(stamp_ns=9, frame_id="base_link"), orientation_covariance=_cov(3, 4),
                 angular_velocity_covariance=_cov(3, 5), linear_acceleration_covariance=_cov(3, 6)),
        Odometry: Odometry(header=Header(stamp_ns=11, frame_id="odom"), child_frame_id="base_link",
                           pose_covariance=_cov(6, 7), twist_covariance=_cov(6, 8)),
        VehicleState: _state(),
        UAVStatus: UAVStatus(current_state=_state()),
    }


def _carries_arrays(info) -> bool:
    if isinstance(info, ti.StructType):
        return info.cls is NDArray or any(_carries_arrays(f.type) for f in info.fields)
    if isinstance(info, (ti.ListType, ti.VarTupleType)):
        return _carries_arrays(info.item_type)
    if isinstance(info, ti.UnionType):
        return any(_carries_arrays(t) for t in info.types)
    return isinstance(info, ti.DictType) and _carries_arrays(info.value_type)


def arrays(msg, path: str = "") -> dict[str, NDArray]:
    """Every NDArray in a message, by field path."""
    if isinstance(msg, NDArray):
        return {path: msg}
    out: dict[str, NDArray] = {}
    if isinstance(msg, msgspec.Struct):
        for f in msg.__struct_fields__:
            out.update(arrays(getattr(msg, f), f"{path}.{f}" if path else f))
    return out


def at_offset(payload: bytes, offset: int) -> memoryview:
    """The payload placed `offset` bytes into a buffer, as a transport hands it over."""
    buf = bytearray(offset + len(payload))
    buf[offset:] = payload
    return memoryview(buf)[offset:]


def decoded_at_every_offset(msg) -> list:
    payload = encode(msg)
    return [decode(at_offset(payload, k), type(msg)) for k in OFFSETS]


def test_the_samples_cover_every_schema_that_carries_arrays():
    carrying = {cls for cls in REGISTRY.values() if _carries_arrays(ti.type_info(cls))}
    assert carrying == set(samples()), "a new array-carrying schema needs a sample here"


@pytest.mark.parametrize("cls", list(samples()), ids=lambda c: c.__name__)
def test_every_array_lands_on_every_offset_and_decodes_aligned(cls):
    msg = samples()[cls]
    want = {p: a.to_numpy() for p, a in arrays(msg).items()}
    raw_offsets: dict[str, set[int]] = {p: set() for p in want}
    for got in decoded_at_every_offset(msg):
        for p, nd in arrays(got).items():
            raw = np.frombuffer(nd.data, dtype=nd.dtype)
            raw_offsets[p].add(raw.ctypes.data % 8)
            a = nd.to_numpy()
            assert a.flags.aligned, f"{cls.__name__}.{p} ({nd.dtype}) decoded at a misaligned address"
            np.testing.assert_array_equal(a, want[p])
    for p, seen in raw_offsets.items():
        assert seen == set(range(8)), f"{cls.__name__}.{p} landed only on offsets {sorted(seen)}"


def test_an_aligned_array_stays_a_zero_copy_view():
    payload = encode(samples()[PointCloud])
    for k in OFFSETS:
        nd = decode(at_offset(payload, k), PointCloud).points
        raw = np.frombuffer(nd.data, dtype=nd.dtype)
        if raw.flags.aligned:
            assert np.shares_memory(nd.to_numpy(), raw)
            return
    pytest.fail("no offset gave an aligned view")


# ------------------------------------------------------------------ consumers (each in its own process)


def _viz() -> None:
    import rerun as rr

    from aeroperception.services.viz import adapters as A
    from aeroperception.services.viz import contract

    rr.init("alignment")
    rec = rr.memory_recording()
    params = SimpleNamespace(**{p.name: p.default for p in contract.PARAMS})
    by_schema = samples()
    logged = set()
    for adapter in A.build_adapters(params):
        msg = by_schema.get(adapter.schema)
        if msg is None:
            continue
        for got in decoded_at_every_offset(msg):
            for entry in adapter.convert(got):
                rr.log(entry.path, *entry.archetypes, static=entry.static)
                logged.add(adapter.key)
    rec.drain_as_bytes()    # flushes: Rerun's Arrow import of every logged batch happens by now
    assert {"perception/obstacles", "perception/costmap", "state/visual_odometry",
            "sensors/camera/left/image", "state/vehicle"} <= logged, logged


def _ros2bridge() -> None:
    from aeroperception.services.ros2bridge.convert import CATALOG, Converter, conversion
    from aeroperception.services.ros2bridge.rmw import make_typestore

    store = make_typestore()
    conv = Converter(store)
    by_schema = samples()
    kinds = {"from_vehicle_state": VehicleState, "from_odometry": Odometry, "from_imu": Imu,
             "from_image": Image, "from_point_cloud": PointCloud}
    done = set()
    for b in CATALOG.values():
        cls = kinds.get(b.convert)
        if cls is None:
            continue
        for got in decoded_at_every_offset(by_schema[cls]):
            cdr = store.serialize_cdr(conversion(conv, b)(got), b.ros_type)
            assert len(cdr) > 0
        done.add(b.convert)
    assert done == set(kinds), done


def _foxglove() -> None:
    import json

    from aeroperception.services.recorder.foxglove import convert

    for cls, msg in samples().items():
        payload = encode(msg)
        outs = [list(convert("key", schema_id(cls), at_offset(payload, k))) for k in OFFSETS]
        assert outs[0], f"{cls.__name__}: nothing exported"
        assert all(o == outs[0] for o in outs), f"{cls.__name__}: export depends on the payload's offset"
        for _topic, _schema, data in outs[0]:
            json.loads(data)


def _lidar() -> None:
    from aeroperception.services.lidar.contract import PARAMS
    from aeroperception.services.lidar.pipeline import ObstaclePipeline, PipelineConfig
    from aeroperception.services.runtime.config import build

    cfg = build(PipelineConfig, PARAMS)
    results = [ObstaclePipeline(cfg).process(got.points.to_numpy(), np.eye(3))
               for got in decoded_at_every_offset(samples()[PointCloud])]
    for r in results[1:]:
        assert len(r.obstacles) == len(results[0].obstacles) and len(r.ground) == len(results[0].ground)
    assert len(results[0].ground) > 0


def _vio() -> None:
    from aeroperception.services.vio.calibration import CameraCalibration
    from aeroperception.services.vio.frontend import FrontEnd
    from aeroperception.services.vio.messages import imu_sample, pixels

    for left, right, image, imu in zip(decoded_at_every_offset(samples()[CameraInfo]),
                                       decoded_at_every_offset(stereo_info(-0.05)),
                                       decoded_at_every_offset(samples()[Image]),
                                       decoded_at_every_offset(samples()[Imu])):
        calib = CameraCalibration.from_camera_infos(left, right)
        fe = FrontEnd(calib)
        px = pixels(image)
        res = fe.process(1, px, px)
        assert res is not None
        imu_sample(imu)


def _detector() -> None:
    from aeroperception.services.detector.contract import BUNDLED_MODEL
    from aeroperception.services.detector.logic import resolve_model_path
    from aeroperception.services.detector.yolo import YoloModel

    model = YoloModel.load(resolve_model_path(BUNDLED_MODEL))
    outs = [model.detect(got.to_numpy(), channels="rgb")[0] for got in decoded_at_every_offset(samples()[Image])]
    assert all(o == outs[0] for o in outs)


CONSUMERS = {"viz": _viz, "ros2bridge": _ros2bridge, "foxglove": _foxglove, "lidar": _lidar, "vio": _vio,
             "detector": _detector}


def _run(name: str) -> None:
    CONSUMERS[name]()


@pytest.mark.parametrize("consumer", list(CONSUMERS))
def test_every_consumer_takes_arrays_from_every_offset(consumer):
    ctx = multiprocessing.get_context("spawn")
    p = ctx.Process(target=_run, args=(consumer,))
    p.start()
    p.join(120)
    if p.is_alive():
        p.kill()
        p.join(5)
        pytest.fail(f"{consumer}: still running after 120 s")
    assert p.exitcode == 0, f"{consumer}: exited with {p.exitcode} (a negative code is a signal: -6 = abort)"
