"""The Ouster decoder (services/lib/lidar/ouster.py) on the real OS-0/1/2-128 captures: against
ouster-sdk's XYZLut and destagger when ouster-sdk is installed (`pip install .[lidar-reference]`
in a venv of its own: it cannot share the test lock), and always against what that comparison
established (points per frame) and the documented geometry. Skipped when ../shared/data is absent."""
from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from aeroperception.services.lib.lidar import ouster as O
from aeroperception.services.lib.lidar.pcap import read_udp
from aeroperception.services.lib.lidar.velodyne import PacketError
from aeroperception.services.runtime.data import shared_data_dir

DATA = shared_data_dir()
OUSTER = DATA / "lidar_pcap" / "ouster" if DATA else None
needs_data = pytest.mark.skipif(OUSTER is None or not OUSTER.is_dir(), reason="../shared/data/lidar_pcap absent")
# capture, metadata, {frame id: returns} (the counts ouster-sdk 1.0.1 decodes), IMU packets
CAPTURES = [
    ("OS-1-128_v2.3.0_1024x10_lb_n3", "OS-1-128_v2.3.0_1024x10", {1795: 107647, 1796: 107357, 1797: 107532}, 30),
    ("OS-0-128-U1_v2.3.0_1024x10", "OS-0-128-U1_v2.3.0_1024x10", {1491: 97299}, 10),
    ("OS-2-128-U1_v2.3.0_1024x10", "OS-2-128-U1_v2.3.0_1024x10", {1259: 119682}, 10),
]


def _frames(pcap_name, meta):
    frames, imu = {}, []
    for d in read_udp(OUSTER / f"{pcap_name}.pcap"):
        if d.dst[1] == meta.imu_port:
            imu.append(O.decode_imu(d.payload))
            continue
        c = O.decode_lidar(meta, d.payload)
        f = frames.setdefault(c.frame_id, {"range": np.zeros((meta.pixels_per_column, meta.columns_per_frame)),
                                           "stamp": np.zeros(meta.columns_per_frame, np.uint64)})
        f["range"][:, c.measurement_id] = np.where(c.valid[:, None], c.fields["range_mm"], 0).T
        f["stamp"][c.measurement_id] = c.stamp_ns
    return frames, imu


@needs_data
@pytest.mark.parametrize("pcap_name,json_name,returns,n_imu", CAPTURES)
def test_every_frame_of_the_real_captures_decodes_whole(pcap_name, json_name, returns, n_imu):
    meta = O.OusterMetadata.load(OUSTER / f"{json_name}.json")
    frames, imu = _frames(pcap_name, meta)
    assert {k: int((f["range"] > 0).sum()) for k, f in frames.items()} == returns
    assert all(np.all(np.diff(f["stamp"].astype(np.int64)) > 0) for f in frames.values())   # every column, in time
    assert len(imu) == n_imu
    g = np.linalg.norm(np.stack([i.accel_g for i in imu]), axis=1)
    assert np.all(np.abs(g - 1.0) < 0.2)          # gravity, plus the recording vehicle's 0.03-0.15 g


@needs_data
@pytest.mark.parametrize("pcap_name,json_name,returns,n_imu", CAPTURES)
def test_points_match_ouster_sdk_xyzlut(pcap_name, json_name, returns, n_imu):
    pytest.importorskip("ouster.sdk")
    from ouster.sdk import core, pcap
    meta = O.OusterMetadata.load(OUSTER / f"{json_name}.json")
    frames, _ = _frames(pcap_name, meta)
    src = pcap.PcapFrameSetSource(str(OUSTER / f"{pcap_name}.pcap"), meta=[str(OUSTER / f"{json_name}.json")])
    info = src.sensor_info[0]
    lut = core.XYZLut(info, use_extrinsics=False)
    seen = 0
    for fs in src:
        scan, ours = fs[0], frames[fs[0].frame_id]
        rng = scan.field(core.ChanField.RANGE)
        np.testing.assert_array_equal(rng, ours["range"])
        np.testing.assert_array_equal(scan.timestamp, ours["stamp"])
        assert np.abs(O.xyz(meta, ours["range"]) - lut(rng)).max() < 1e-6
        np.testing.assert_array_equal(core.destagger(info, rng), O.destagger(meta, ours["range"]))
        seen += 1
    assert seen == len(returns)


def _meta(**fmt):
    m = {"beam_altitude_angles": [0.0, 10.0], "beam_azimuth_angles": [0.0, 0.0], "lidar_origin_to_beam_origin_mm": 0.0,
         "lidar_to_sensor_transform": list(np.eye(4).ravel()),
         "data_format": {"columns_per_frame": 4, "columns_per_packet": 2, "pixels_per_column": 2,
                         "pixel_shift_by_row": [1, 0], "udp_profile_lidar": "RNG19_RFL8_SIG16_NIR16", **fmt}}
    return O.OusterMetadata.from_json(json.loads(json.dumps(m)))


def test_geometry_follows_the_documented_frame():
    meta = _meta()
    p = O.xyz(meta, np.full((2, 4), 1000.0))
    np.testing.assert_allclose(p[0, 0], [1.0, 0.0, 0.0], atol=1e-12)        # column 0 looks along +x
    np.testing.assert_allclose(p[0, 1], [0.0, -1.0, 0.0], atol=1e-12)       # the encoder turns clockwise
    assert p[1, 0, 2] == pytest.approx(np.sin(np.radians(10.0)))


def test_a_packet_of_the_wrong_size_or_column_is_refused_with_the_reason():
    meta = _meta()
    with pytest.raises(PacketError, match="bytes"):
        O.decode_lidar(meta, bytes(10))
    col = struct.pack("<QHH", 1, 9, 1) + bytes(24)          # measurement id 9 of 4 columns
    with pytest.raises(PacketError, match="measurement id 9"):
        O.decode_lidar(meta, bytes(32) + col * 2 + bytes(32))
