"""The lidar_driver's scan assembly (services/lidar_driver/logic.py), fed the real captures'
packets directly: whole rotations with ring and time, and what a network does to a stream
(garbage, truncation, reordering, loss) counted by reason, never raised."""
from __future__ import annotations

import numpy as np
import pytest

from aeroperception.services.lib.lidar.pcap import read_udp
from aeroperception.services.lidar_driver import contract
from aeroperception.services.lidar_driver.logic import DriverConfig, ScanAssembler
from aeroperception.services.runtime.config import build
from aeroperception.services.runtime.data import shared_data_dir

DATA = shared_data_dir()
PCAPS = DATA / "lidar_pcap" if DATA else None
pytestmark = pytest.mark.skipif(PCAPS is None or not PCAPS.is_dir(), reason="../shared/data/lidar_pcap absent")


def _cfg(**changes) -> DriverConfig:
    return build(DriverConfig, contract.PARAMS, **{"min_range_m": 0.1, "max_range_m": 200.0, "time_source": "sensor",
                                                   **changes})


def _run(cfg, packets):
    a, scans, last = ScanAssembler(cfg), [], 0
    for stamp, payload in packets:
        scans += a.feed(payload, stamp)
        last = stamp
    return a, scans + a.flush(last + 10**9)


def _packets(name):
    return [(d.stamp_ns, d.payload) for d in read_udp(PCAPS / name)]


def test_hdl32_capture_gives_whole_rotations_with_ring_and_time():
    a, scans = _run(_cfg(), _packets("velodyne/hdl32_example.pcap"))
    assert [round(s.coverage, 2) for s in scans] == [1.0] * 5
    assert all(43000 < len(s.xyz_m) < 45000 for s in scans)
    for s in scans:
        assert s.time_offset_s.min() == 0.0 and 0.08 < s.time_offset_s.max() < 0.09     # a 10 Hz sweep
        assert set(np.unique(s.ring)) == set(range(32))
    assert a.counts["position_packets"] == 100 and a.counts["scans_dropped"] == 2      # the partial ends


def test_ouster_capture_gives_one_scan_per_frame():
    cfg = _cfg(vendor="ouster", metadata_path=str(PCAPS / "ouster/OS-1-128_v2.3.0_1024x10.json"))
    a, scans = _run(cfg, _packets("ouster/OS-1-128_v2.3.0_1024x10_lb_n3.pcap"))
    assert [len(s.xyz_m) for s in scans] == [107646, 107350, 107529]     # ouster-sdk's returns, minus < 0.1 m
    assert a.counts["imu_packets_on_lidar_port"] == 30 and a.counts["lost_columns"] == 0
    top = scans[0].ring == 127
    assert scans[0].xyz_m[top, 2].mean() > scans[0].xyz_m[~top, 2].mean()    # ring 127 is the highest beam


def test_garbage_and_truncated_packets_are_counted_and_the_scans_still_come():
    pk = _packets("velodyne/hdl32_example.pcap")
    bad = [(pk[0][0], b"garbage"), (pk[0][0], pk[5][1][:600]), (pk[0][0], b"\xff" * 1206)]
    a, scans = _run(_cfg(), pk[:300] + bad + pk[300:])
    assert a.counts["bad_packets"] == 3 and len(scans) == 5


def test_reordered_packets_are_dropped_and_lost_ones_counted_the_scan_published_with_what_arrived():
    pk = _packets("velodyne/hdl32_example.pcap")
    pk = [p for p in pk if len(p[1]) == 1206]
    swapped = pk[:200] + [pk[201], pk[200]] + pk[202:]
    a, scans = _run(_cfg(), swapped)
    assert a.counts["reordered_packets"] == 1
    lossy = [p for i, p in enumerate(pk) if not 300 <= i < 320]          # 20 packets (~41 deg) lost
    a, scans = _run(_cfg(), lossy)
    assert a.counts["lost_packets"] == 20
    assert sorted(round(s.coverage, 2) for s in scans)[0] == pytest.approx(0.88, abs=0.02)


def test_a_sensor_clock_that_jumps_back_restarts_the_stream_instead_of_dropping_it_for_ever():
    """A replay started over, a reboot, a PTP re-sync: the packets' clock goes 0.48 s back. They
    were 'reordered' and dropped until the clock caught up again (up to half an hour); now the scan
    in progress ends and every rotation of the second pass comes out too."""
    pk = [p for p in _packets("velodyne/hdl32_example.pcap") if len(p[1]) == 1206]
    t_end = pk[-1][0]
    again = [(t_end + 10**6 + t - pk[0][0], payload) for t, payload in pk]   # arrival keeps going forward
    a, scans = _run(_cfg(time_source="host"), pk + again)
    assert a.counts["clock_jumps"] == 1 and a.counts["reordered_packets"] == 0
    assert sum(round(s.coverage, 2) == 1.0 for s in scans) == 10
    assert np.all(np.diff([s.stamp_ns for s in scans]) > 0)


def test_an_ouster_whose_frame_ids_restart_is_taken_from_the_restart():
    cfg = _cfg(vendor="ouster", metadata_path=str(PCAPS / "ouster/OS-1-128_v2.3.0_1024x10.json"))
    pk = _packets("ouster/OS-1-128_v2.3.0_1024x10_lb_n3.pcap")
    a, scans = _run(cfg, pk + [(t + 10**9, payload) for t, payload in pk])
    assert a.counts["clock_jumps"] == 1 and len(scans) == 6


def test_a_burst_fed_at_once_gives_what_feeding_packets_one_by_one_gives():
    pk = _packets("velodyne/hdl32_example.pcap")
    bad = [(pk[0][0], b"garbage"), (pk[0][0], b"\xff" * 1206)]
    pk = pk[:300] + bad + pk[300:]
    one, scans_one = _run(_cfg(), pk)
    many, scans_many = ScanAssembler(_cfg()), []
    for i in range(0, len(pk), 37):                            # bursts as a socket drain gives them
        scans_many += many.feed_many([(payload, t) for t, payload in pk[i:i + 37]])
    scans_many += many.flush(pk[-1][0] + 10**9)
    assert many.counts == one.counts and len(scans_many) == len(scans_one) == 5
    for a, b in zip(scans_one, scans_many):
        assert a.stamp_ns == b.stamp_ns and np.array_equal(a.xyz_m, b.xyz_m) and np.array_equal(a.ring, b.ring)
        assert np.array_equal(a.time_offset_s, b.time_offset_s) and a.coverage == b.coverage


def test_ouster_imu_packets_in_the_sensor_frame_in_si_units():
    from aeroperception.services.lib.lidar import ouster

    cfg = _cfg(vendor="ouster", metadata_path=str(PCAPS / "ouster/OS-1-128_v2.3.0_1024x10.json"), imu_port=7503)
    a = ScanAssembler(cfg)
    raw = [d for d in read_udp(PCAPS / "ouster/OS-1-128_v2.3.0_1024x10_lb_n3.pcap") if d.dst[1] == 7503]
    imu = [a.imu(d.payload, d.stamp_ns) for d in raw]
    assert len(imu) == 30 and a.counts["imu_packets"] == 30
    ref = ouster.decode_imu(raw[0].payload)
    r = a.meta.imu_to_sensor[:3, :3]
    np.testing.assert_allclose(imu[0].accel_mps2, r @ ref.accel_g * 9.80665)
    np.testing.assert_allclose(imu[0].gyro_radps, r @ np.radians(ref.gyro_dps))
    assert imu[0].stamp_ns == ref.accel_stamp_ns                 # time_source sensor
    acc = np.array([s.accel_mps2 for s in imu])
    assert 9.3 < acc[:, 2].mean() < 10.3                         # upright: the specific force points up
    assert a.imu(b"short", 0) is None and a.counts["bad_imu_packets"] == 1


def test_imu_port_on_a_velodyne_is_refused():
    with pytest.raises(ValueError, match="only an Ouster sends IMU packets"):
        ScanAssembler(_cfg(imu_port=7503))


def test_a_scan_covering_too_little_is_dropped_with_its_reason():
    a, scans = _run(_cfg(min_coverage=0.9), _packets("velodyne/vlp16_velodyne_example.pcap"))
    assert scans == []
    assert a.counts["scans_dropped"] == 2
    assert any(k.startswith("scans_dropped: 77% of the rotation") for k in a.counts)


def test_random_datagrams_never_raise():
    rng = np.random.default_rng(0)
    a = ScanAssembler(_cfg())
    for n in rng.integers(0, 1400, 300):
        a.feed(rng.integers(0, 256, n, dtype=np.uint8).tobytes(), 0)
    a.feed(b"", 0)
    assert a.counts["packets"] == 301
