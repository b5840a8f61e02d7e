"""ros2bridge's ROS -> ours direction without Zenoh: the PointCloud2 field-layout decoder (vendor
layouts, big-endian, padding, NaNs, missing optional fields, refusals), images, camera infos, IMU,
and the `inputs` configuration. Messages are built with rosbags and sent through CDR and back, as
the bridge receives them."""
import math

import cv2
import numpy as np
import pytest

from aeroperception.services.ros2bridge import contract, inbound
from aeroperception.services.ros2bridge.bridge import InputBridge, RosBridgeConfig
from aeroperception.services.ros2bridge.inbound import CLOUD, COMPRESSED, IMAGE, INFO, Source
from aeroperception.services.ros2bridge.pointcloud2 import LayoutError, decode
from aeroperception.services.ros2bridge.rmw import make_typestore
from aeroperception.services.runtime.config import build

STORE = make_typestore()
T = STORE.types
F32, F64, U8, U16, U32 = 7, 8, 2, 4, 6
STAMP = (1_700_000_000, 123_456_789)
STAMP_NS = STAMP[0] * 1_000_000_000 + STAMP[1]
FEEDABLE = list(contract.OUTPUTS)


def ros_header(frame="lidar"):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=STAMP[0], nanosec=STAMP[1]),
                                    frame_id=frame)


def via_cdr(msg, typ):
    return STORE.deserialize_cdr(bytes(STORE.serialize_cdr(msg, typ)), typ)


def cloud(columns, point_step, bigendian=False, height=1, row_pad=0, dense=True):
    """A PointCloud2 of `columns` [(name, datatype, values)] packed at their natural offsets in
    declaration order, each point padded to point_step, each row padded by row_pad bytes."""
    order = ">" if bigendian else "<"
    codes = {F32: "f4", F64: "f8", U8: "u1", U16: "u2", U32: "u4"}
    names, formats, offsets, off = [], [], [], 0
    for name, dt, _ in columns:
        names.append(name)
        formats.append(order + codes[dt])
        offsets.append(off)
        off += np.dtype(codes[dt]).itemsize
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    n = len(columns[0][2])
    arr = np.zeros(n, dtype)
    for name, _, values in columns:
        arr[name] = values
    width = n // height
    rows = arr.view(np.uint8).reshape(height, width * point_step)
    data = np.hstack([rows, np.full((height, row_pad), 0xAB, np.uint8)]).reshape(-1)
    fields = [T["sensor_msgs/msg/PointField"](name=nm, offset=o, datatype=dt, count=1)
              for (nm, dt, _), o in zip(columns, offsets)]
    msg = T["sensor_msgs/msg/PointCloud2"](header=ros_header(), height=height, width=width, fields=fields,
                                           is_bigendian=bigendian, point_step=point_step,
                                           row_step=width * point_step + row_pad, data=data, is_dense=dense)
    return via_cdr(msg, CLOUD)


RNG = np.random.default_rng(0)
XYZ = RNG.uniform(-50, 50, (240, 3)).astype(np.float32)
INTENSITY = RNG.uniform(0, 255, 240).astype(np.float32)
RING = (np.arange(240) % 16).astype(np.uint16)
TIME_S = np.linspace(0, 0.099, 240).astype(np.float32)


def xyz_columns(xyz=XYZ):
    return [("x", F32, xyz[:, 0]), ("y", F32, xyz[:, 1]), ("z", F32, xyz[:, 2])]


def test_velodyne_layout_gives_points_intensity_ring_and_time():
    msg = cloud(xyz_columns() + [("intensity", F32, INTENSITY), ("ring", U16, RING), ("time", F32, TIME_S)], 22)
    pts, extra = decode(msg, STAMP_NS)
    assert np.array_equal(pts, XYZ) and np.array_equal(extra["intensity"], INTENSITY)
    assert extra["ring"].dtype == np.uint16 and np.array_equal(extra["ring"], RING)
    assert np.array_equal(extra["time_offset_s"], TIME_S)


def test_ouster_layout_with_ns_time_and_padding_to_48_bytes():
    t_ns = np.round(TIME_S.astype(np.float64) * 1e9).astype(np.uint32)
    cols = xyz_columns() + [("_pad", F32, np.zeros(240)), ("intensity", F32, INTENSITY), ("t", U32, t_ns),
                            ("reflectivity", U16, RING * 3), ("ring", U16, RING), ("ambient", U16, RING),
                            ("range", U32, t_ns)]
    pts, extra = decode(cloud(cols, 48), STAMP_NS)
    assert np.array_equal(pts, XYZ) and np.array_equal(extra["ring"], RING)
    assert np.allclose(extra["time_offset_s"], t_ns * 1e-9, atol=1e-9)


def test_livox_layout_line_is_the_ring_and_absolute_ns_timestamps_become_offsets():
    line = (np.arange(240) % 4).astype(np.uint8)
    stamps = STAMP_NS + TIME_S.astype(np.float64) * 1e9
    cols = xyz_columns() + [("intensity", F32, INTENSITY), ("tag", U8, line), ("line", U8, line),
                            ("timestamp", F64, stamps)]
    pts, extra = decode(cloud(cols, 26), STAMP_NS)
    assert np.array_equal(pts, XYZ) and np.array_equal(extra["ring"], line.astype(np.uint16))
    assert np.allclose(extra["time_offset_s"], TIME_S, atol=1e-6)


def test_big_endian_clouds_decode_to_the_same_values():
    cols = xyz_columns() + [("intensity", F32, INTENSITY), ("ring", U16, RING)]
    pts, extra = decode(cloud(cols, 20, bigendian=True), STAMP_NS)
    assert np.array_equal(pts, XYZ) and np.array_equal(extra["ring"], RING)


def test_organized_cloud_with_padded_rows():
    pts, extra = decode(cloud(xyz_columns() + [("intensity", F32, INTENSITY)], 16, height=16, row_pad=7), STAMP_NS)
    assert np.array_equal(pts, XYZ) and np.array_equal(extra["intensity"], INTENSITY)


def test_non_finite_points_are_dropped_with_their_fields_whatever_is_dense_says():
    xyz = XYZ.copy()
    xyz[[3, 50, 100], [0, 1, 2]] = [np.nan, np.inf, np.nan]
    for dense in (False, True):
        pts, extra = decode(cloud(xyz_columns(xyz) + [("ring", U16, RING)], 16, dense=dense), STAMP_NS)
        keep = np.ones(240, bool)
        keep[[3, 50, 100]] = False
        assert np.array_equal(pts, XYZ[keep]) and np.array_equal(extra["ring"], RING[keep])


def test_missing_optional_fields_are_simply_absent():
    pts, extra = decode(cloud(xyz_columns(), 12), STAMP_NS)
    assert np.array_equal(pts, XYZ) and extra == {}
    pc = inbound.point_cloud(cloud(xyz_columns(), 12))
    assert pc.intensity is None and pc.ring is None and pc.time_offset_s is None
    assert pc.header.stamp_ns == STAMP_NS and pc.header.frame_id == "lidar"


@pytest.mark.parametrize("cols, step, why", [
    ([("x", F32, XYZ[:, 0]), ("y", F32, XYZ[:, 1])], 8, "z"),
    ([("x", F64, XYZ[:, 0]), ("y", F64, XYZ[:, 1]), ("z", F64, XYZ[:, 2])], 24, "x"),
])
def test_a_layout_without_float32_xyz_is_refused_naming_it(cols, step, why):
    with pytest.raises(LayoutError, match=f"float32 x, y, z.*{why}"):
        decode(cloud(cols, step), STAMP_NS)


def test_truncated_data_and_a_time_field_in_another_unit_are_refused():
    msg = cloud(xyz_columns(), 12)
    msg.data = msg.data[:-5]
    with pytest.raises(LayoutError, match="bytes"):
        decode(msg, STAMP_NS)
    with pytest.raises(LayoutError, match="not that unit"):   # "time" in ns where seconds are meant
        decode(cloud(xyz_columns() + [("time", F32, TIME_S * 1e9)], 16), STAMP_NS)


def ros_image(pixels, encoding, step=None, bigendian=False):
    h, w = pixels.shape[:2]
    row = pixels[0].nbytes
    step = step or row
    raw = np.zeros((h, step), np.uint8)
    px = pixels.astype(pixels.dtype.newbyteorder(">")) if bigendian else pixels
    raw[:, :row] = np.ascontiguousarray(px).view(np.uint8).reshape(h, row)
    return via_cdr(T[IMAGE](header=ros_header("cam0"), height=h, width=w, encoding=encoding,
                            is_bigendian=int(bigendian), step=step, data=raw.reshape(-1)), IMAGE)


@pytest.mark.parametrize("encoding, shape, dtype", [("mono8", (5, 7), np.uint8), ("mono16", (5, 7), np.uint16),
                                                    ("rgb8", (5, 7, 3), np.uint8), ("bgr8", (5, 7, 3), np.uint8)])
@pytest.mark.parametrize("pad", [0, 9])
def test_raw_images_respect_step_padding(encoding, shape, dtype, pad):
    px = RNG.integers(0, np.iinfo(dtype).max, shape).astype(dtype)
    img = inbound.image(ros_image(px, encoding, step=px[0].nbytes + pad))
    assert img.encoding == encoding and np.array_equal(img.to_numpy(), px)
    assert (img.header.stamp_ns, img.header.frame_id) == (STAMP_NS, "cam0")


def test_big_endian_mono16_and_unsupported_encodings():
    px = RNG.integers(0, 65535, (4, 6)).astype(np.uint16)
    assert np.array_equal(inbound.image(ros_image(px, "mono16", bigendian=True)).to_numpy(), px)
    with pytest.raises(ValueError, match="yuv422"):
        inbound.image(ros_image(np.zeros((2, 4), np.uint8), "yuv422"))


def test_compressed_png_is_lossless_and_jpeg_decodes_to_bgr8():
    px = RNG.integers(0, 255, (24, 32), dtype=np.uint8)
    msg = via_cdr(T[COMPRESSED](header=ros_header("cam0"), format="mono8; png compressed mono8",
                                data=np.frombuffer(cv2.imencode(".png", px)[1].tobytes(), np.uint8)), COMPRESSED)
    img = inbound.compressed_image(msg)
    assert img.encoding == "mono8" and np.array_equal(img.to_numpy(), px)
    ramp = (np.add.outer(np.arange(24), np.arange(32)) * 4).astype(np.uint8)   # smooth: JPEG keeps it close
    color = np.dstack([ramp, ramp // 2, 255 - ramp])
    msg.data, msg.format = np.frombuffer(cv2.imencode(".jpg", color)[1].tobytes(), np.uint8), "jpeg"
    img = inbound.compressed_image(msg)
    assert img.encoding == "bgr8" and np.abs(img.to_numpy().astype(int) - color).mean() < 3
    msg.format = "16UC1; compressedDepth png"
    with pytest.raises(ValueError, match="compressedDepth"):
        inbound.compressed_image(msg)


def test_camera_info_keeps_k_d_r_p_and_takes_the_mount_as_t_body_camera():
    K = [458.654, 0.0, 367.215, 0.0, 457.296, 248.375, 0.0, 0.0, 1.0]
    D = [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0]
    P = [458.654, 0.0, 367.215, 0.0, 0.0, 457.296, 248.375, 0.0, 0.0, 0.0, 1.0, 0.0]
    msg = via_cdr(T[INFO](header=ros_header("cam0"), height=480, width=752, distortion_model="plumb_bob",
                          d=np.array(D), k=np.array(K), r=np.eye(3).reshape(-1), p=np.array(P),
                          binning_x=0, binning_y=0,
                          roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                    do_rectify=False)), INFO)
    cfg = build(RosBridgeConfig, contract.PARAMS, **{"inputs": "/cam0/camera_info=sensors/camera/left/info",
                                                   "left_mount_x_m": 0.1, "left_mount_pitch_deg": 90.0})
    info = Source("/cam0/camera_info", "sensors/camera/left/info", INFO).converter(
        {"left": cfg.t_body_camera("left")})(msg)
    assert np.array_equal(info.K.to_numpy().ravel(), K) and np.array_equal(info.D.to_numpy(), D)
    assert np.array_equal(info.P.to_numpy().ravel(), P) and (info.width, info.height) == (752, 480)
    assert info.T_body_camera.position.x == pytest.approx(0.1)
    # pitched +90 deg: the optical axis (z) looks down the body's -z
    from aeroperception.services.runtime.rotations import quat_to_rotmat
    q = info.T_body_camera.orientation
    assert quat_to_rotmat(np.array([q.w, q.x, q.y, q.z])) @ [0, 0, 1] == pytest.approx([0, 0, -1], abs=1e-9)
    msg.distortion_model = "equidistant"
    with pytest.raises(ValueError, match="equidistant"):
        inbound.camera_info(msg, np.eye(4))


def ros_imu(frame="imu_link", ocov0=-1.0):
    v = T["geometry_msgs/msg/Vector3"]
    return via_cdr(T["sensor_msgs/msg/Imu"](
        header=ros_header(frame), orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.array([ocov0] + [0.0] * 8), angular_velocity=v(x=0.04, y=-0.39, z=0.26),
        angular_velocity_covariance=np.eye(3).reshape(-1) * 1e-4, linear_acceleration=v(x=9.9, y=-0.07, z=-4.4),
        linear_acceleration_covariance=np.zeros(9)), "sensor_msgs/msg/Imu")


def test_imu_values_covariances_and_no_orientation_estimate():
    m = inbound.imu(ros_imu())
    assert (m.angular_velocity_radps.y, m.linear_acceleration_mps2.z) == (-0.39, -4.4)
    assert not m.has_orientation and m.orientation_covariance is None
    assert np.array_equal(m.angular_velocity_covariance.to_numpy(), np.eye(3) * 1e-4)
    assert m.linear_acceleration_covariance is None     # all zeros: unknown
    assert inbound.imu(ros_imu(ocov0=0.01)).has_orientation
    with pytest.raises(ValueError, match="NED"):
        inbound.imu(ros_imu("imu_link_ned"))


def cfg_of(**params):
    return build(RosBridgeConfig, contract.PARAMS, **params)


def test_inputs_name_the_topic_feeding_each_key_and_its_ros_type():
    cfg = cfg_of(inputs="/velodyne_points=sensors/lidar/points, cam/image_raw/compressed=sensors/camera/left/image,"
                        "/imu/data=sensors/imu")
    assert cfg.sources(FEEDABLE) == [Source("/velodyne_points", "sensors/lidar/points", CLOUD),
                                     Source("/aero/cam/image_raw/compressed", "sensors/camera/left/image", COMPRESSED),
                                     Source("/imu/data", "sensors/imu", "sensor_msgs/msg/Imu")]
    assert cfg_of(inputs="/cam/image_raw=sensors/camera/right/image").sources(FEEDABLE)[0].ros_type == IMAGE


@pytest.mark.parametrize("params, why", [
    ({"inputs": "/x=sensors/camera/down/image"}, "sensors/camera/down/image cannot be fed"),
    ({"inputs": "/x"}, "not ros_topic=our_key"),
    ({"inputs": "/a=sensors/imu,/b=sensors/imu"}, "fed by two topics"),
    ({"inputs": "imu=sensors/imu", "topics": "sensors/imu"}, "/aero/imu is published by this bridge"),
    ({"inputs": "/a=sensors/camera/left/image", "left_mount_z_m": 0.1}, "left_mount_z_m: no sensors/camera/left/info"),
])
def test_inputs_refused_at_start_naming_why(params, why):
    with pytest.raises(ValueError, match=why):
        cfg_of(**params).sources(FEEDABLE)


def test_a_sample_that_fails_to_convert_is_counted_and_dropped():
    published, reported = [], []
    gate = InputBridge(Source("/p", "sensors/lidar/points", CLOUD), STORE.deserialize_cdr, inbound.point_cloud,
                       published.append, lambda k, e: reported.append((k, e)))
    gate.on_sample(b"\x00\x01\x00\x00garbage")
    bad = cloud([("x", F32, XYZ[:, 0]), ("y", F32, XYZ[:, 1])], 8)
    gate.on_sample(bytes(STORE.serialize_cdr(bad, CLOUD)))
    gate.on_sample(bytes(STORE.serialize_cdr(cloud(xyz_columns(), 12), CLOUD)))
    assert (gate.received, gate.errors, len(published)) == (3, 2, 1)
    assert reported[1][0] == "/p" and "float32 x, y, z" in reported[1][1]
    assert not math.isnan(gate.convert_ms)
