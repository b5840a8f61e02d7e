"""The drift term of VIO's pose covariance (services/vio/drift.py): grows with distance flown and
yaw turned, not with hovering jitter, and is honest (NEES ~3) on a drift of the modelled size."""
import numpy as np

from aeroperception.services.vio.drift import DriftConfig, DriftCovariance


def pose(x: float, y: float = 0.0, z: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, y, z]
    return T


def test_covariance_grows_monotonically_along_a_straight_flight():
    d = DriftCovariance()
    variances = []
    for x in np.arange(0.0, 100.0, 0.25):   # 5 m/s at 20 Hz
        d.update(pose(x, z=4.0))
        variances.append(np.diag(d.covariance()))
    v = np.array(variances)
    assert np.all(np.diff(v[:, :3], axis=0) >= 0) and np.all(np.diff(v[:, 5]) >= 0)
    assert v[0, :3].max() == 0.0
    assert np.isclose(d.distance_m, 99.75, atol=0.01)
    sig = np.sqrt(v[-1])
    assert np.allclose(sig[:2], DriftConfig.drift_xy_frac * 99.75, rtol=0.01)   # 0.25 m after 100 m
    assert np.isclose(sig[2], DriftConfig.drift_z_frac * 99.75, rtol=0.01)
    assert sig[3] == 0.0 and sig[4] == 0.0   # roll, pitch: observable from gravity


def test_hovering_jitter_does_not_count_as_distance_but_turning_grows_yaw():
    d = DriftCovariance()
    rng = np.random.default_rng(1)
    for _ in range(2000):   # 100 s of hover with 1 cm jitter
        d.update(pose(*rng.normal(0, 0.01, 3)))
    assert d.distance_m < 0.5 and d.covariance()[0, 0] < 0.01 ** 2
    for k in range(200):     # turn on the spot, 2 full turns
        d.update(pose(0.0, yaw=k * 2 * np.pi * 2 / 200))
    assert np.isclose(d.turned_rad, 4 * np.pi, rtol=0.05)
    assert d.covariance()[5, 5] > (DriftConfig.yaw_per_rad * 4 * np.pi * 0.9) ** 2
    d.reset()
    assert not d.covariance().any()


def test_nees_is_about_3_on_a_synthetic_drift_of_the_modelled_size():
    """Drift as VIO shows it: an error proportional to distance flown (a per-flight scale and
    heading error), of the size the model claims; NEES of position over the flights ~3."""
    cfg = DriftConfig()
    rng = np.random.default_rng(7)
    nees = []
    for _ in range(400):
        d = DriftCovariance(cfg)
        rate = rng.normal(0.0, [cfg.drift_xy_frac, cfg.drift_xy_frac, cfg.drift_z_frac])   # error per metre
        path = np.cumsum(np.full(300, 0.5))
        for s in path:
            d.update(pose(s, 0.0, 4.0))
            e = rate * d.distance_m
            S = d.covariance()[:3, :3]
            if d.distance_m > 1.0:
                nees.append(e @ np.linalg.solve(S, e))
    assert 2.7 < np.mean(nees) < 3.3, np.mean(nees)
