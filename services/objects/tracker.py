"""Multi-object tracker over world positions: ByteTrack-style two-pass association, a constant-
velocity Kalman filter per track.

Why two passes: a detection the detector is unsure of (low score) is still good evidence for a
track that already exists, but not enough to start one. So high-score detections are matched
first to every track, low-score ones then to the tracks left over; only unmatched high-score
detections start tracks. A track never changes class (detections match only tracks of their
class), is confirmed after `confirm_hits` hits and is deleted after `lost_timeout_s` unseen.
Matching is optimal per pass (Hungarian) over the squared Mahalanobis distance, gated by it and by
a plain distance (a far detection's wide covariance must not capture a track metres away).
"""
from __future__ import annotations

import statistics
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from aeroperception.services.runtime import param

from .projection import Measurement

CHI2_3DOF_99 = 11.345                   # squared Mahalanobis gate, 3 degrees of freedom, 99 %
HORIZONTAL = np.diag([1.0, 1.0, 0.0])   # the axes a track's velocity moves along (east, north)
_FAR = 1e9


def _horizontal_sigma(cov: np.ndarray) -> float:
    """1 sigma along the horizontal axis a covariance (3x3 or larger, position first) is widest on."""
    return float(np.sqrt(np.linalg.eigvalsh(cov[:2, :2])[-1]))


@dataclass(frozen=True)
class ObjectTrackerConfig:
    """The tracker's parameters (defaults, units and ranges, and what each does: contract.PARAMS)."""

    confirm_hits: int = param("confirm_hits")
    lost_timeout_s: float = param("lost_timeout_s")
    tentative_timeout_s: float = param("tentative_timeout_s")
    high_score: float = param("high_score")
    low_score: float = param("min_score")
    gate_distance_m: float = param("gate_distance_m")
    accel_noise_mps2: float = param("accel_sigma_mps2")   # constant-velocity model: white acceleration, 1 sigma
    forget_s: float = param("forget_s")
    coast_tau_s: float = param("coast_tau_s")
    partial_ratio: float = param("partial_ratio")
    partial_scale: float = param("partial_scale")
    crowd_scale: float = param("crowd_scale")
    confirm_scale: float = param("confirm_scale")
    partial_sigma_scale: float = param("partial_sigma_scale")
    birth_sigma_m: float = param("birth_sigma_m")
    birth_spacing_m: float = param("birth_spacing_m")
    initial_speed_mps: float = 2.0      # 1 sigma of a new track's unknown velocity (not a parameter)


@dataclass
class Observation:
    """One detection placed in the world (projection.Measurement) with its class and score."""

    measurement: Measurement
    class_id: int
    class_name: str
    score: float
    box_scale: float = 0.0              # the box's height over its class's typical one seen from there (0: unknown)
    cut: bool = False                   # the box touches the image's edge: part of the object is outside
    length_m: float = 0.0               # its class's typical length (the footprint's longer side; 0: unknown)


@dataclass
class Track:
    track_id: int
    class_id: int
    class_name: str
    x: np.ndarray                       # [east, north, up, ve, vn, vu]
    P: np.ndarray                       # 6x6
    stamp_ns: int                       # time x is for
    first_seen_ns: int
    last_seen_ns: int
    hits: int = 1
    best_score: float = 0.0
    range_m: float = 0.0
    confirmed: bool = False
    seen_x: np.ndarray | None = None    # position and its 3x3 covariance just after the last hit
    seen_P: np.ndarray | None = None
    seen_ns: int = 0                    # when a detection last moved it
    scales: list[float] = field(default_factory=list)        # the last whole boxes' box_scale
    partial_run: int = 0                # partial views in a row
    whole_views: int = 0                # whole boxes (box_scale known) since the track started
    fitting_views: int = 0              # of which filled confirm_scale of the class's typical size


@dataclass
class Events:
    confirmed: list[Track] = field(default_factory=list)
    lost: list[Track] = field(default_factory=list)
    reacquired: list[Track] = field(default_factory=list)


class Tracker:
    """Step it with `update(stamp_ns, observations)` once per detection frame, in stamp order."""

    def __init__(self, config: ObjectTrackerConfig):
        self.tracks: list[Track] = []
        self.lost: list[Track] = []     # confirmed tracks unseen for lost_timeout_s, kept for forget_s
        self.next_id = 1
        self.configure(config)

    def configure(self, config: ObjectTrackerConfig) -> None:
        self.config = config
        self._motions: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    # ------------------------------------------------------------ Kalman filter

    def _predict(self, t: Track, stamp_ns: int) -> None:
        dt = (stamp_ns - t.stamp_ns) * 1e-9
        if dt <= 0:
            return
        f, q = self._motion(dt)
        t.x, t.P, t.stamp_ns = f @ t.x, f @ t.P @ f.T + q, stamp_ns
        if self.config.coast_tau_s > 0 and stamp_ns - int(dt * 1e9) > t.seen_ns:    # coasting since before this step
            # The velocity, and what is uncertain about it, decay together: a track kept alive for
            # seconds by partial views must not come out of it so loose that its next whole view
            # (biased by a metre near) throws it, with a velocity, past where it is.
            a = np.exp(-dt / self.config.coast_tau_s)
            t.x[3:] *= a
            t.P[3:, :] *= a
            t.P[:, 3:] *= a

    def _motion(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Transition and process noise for a step of dt s (most tracks share a frame's dt)."""
        hit = self._motions.get(dt)
        if hit is not None:
            return hit
        if len(self._motions) > 32:
            self._motions.clear()
        f = np.eye(6)
        f[:3, 3:] = np.eye(3) * dt
        q = self.config.accel_noise_mps2 ** 2 * np.kron([[dt ** 4 / 4, dt ** 3 / 2], [dt ** 3 / 2, dt ** 2]], HORIZONTAL)
        self._motions[dt] = (f, q)
        return f, q

    @staticmethod
    def _correct(t: Track, m: Measurement) -> None:
        k = t.P[:, :3] @ np.linalg.inv(t.P[:3, :3] + m.covariance_m2)       # 6x3 gain
        t.x = t.x + k @ (m.position_m - t.x[:3])
        p = t.P - k @ t.P[:3, :]
        t.P = (p + p.T) / 2

    # ------------------------------------------------------------ association

    @staticmethod
    def _differences(tracks: list[Track], obs: list[Observation]) -> tuple[np.ndarray, np.ndarray]:
        """(T, O, 3) position differences and (T, O) squared Mahalanobis distances of every
        (track, observation) pair. One batched solve: the cost stays flat in Python."""
        pos = np.array([t.x[:3] for t in tracks])                               # (T, 3)
        cov = np.array([t.P[:3, :3] for t in tracks])                           # (T, 3, 3)
        z = np.array([o.measurement.position_m for o in obs])                   # (O, 3)
        r = np.array([o.measurement.covariance_m2 for o in obs])                # (O, 3, 3)
        diff = z[None, :, :] - pos[:, None, :]
        return diff, np.einsum("toi,toi->to", diff, np.linalg.solve(cov[:, None] + r[None], diff[..., None])[..., 0])

    def _costs(self, tracks: list[Track], obs: list[Observation]) -> np.ndarray:
        """Squared Mahalanobis distance of every (track, observation) pair; _FAR where the class
        differs or a gate refuses."""
        diff, d2 = self._differences(tracks, obs)
        same = np.array([t.class_id for t in tracks])[:, None] == np.array([o.class_id for o in obs])[None, :]
        ok = same & (np.linalg.norm(diff, axis=2) <= self.config.gate_distance_m) & (d2 <= CHI2_3DOF_99)
        return np.where(ok, d2, _FAR)

    def _match(self, tracks: list[Track], obs: list[Observation]) -> tuple[list[tuple[int, int]], list[int], list[int]]:
        """(track index, observation index) pairs, unmatched tracks, unmatched observations."""
        if not tracks or not obs:
            return [], list(range(len(tracks))), list(range(len(obs)))
        c = self._costs(tracks, obs)
        rows, cols = linear_sum_assignment(c)
        pairs = [(i, j) for i, j in zip(rows, cols) if c[i, j] < _FAR]
        mt, mo = {i for i, _ in pairs}, {j for _, j in pairs}
        return pairs, [i for i in range(len(tracks)) if i not in mt], [j for j in range(len(obs)) if j not in mo]

    # ------------------------------------------------------------ one frame

    def update(self, stamp_ns: int, observations: list[Observation]) -> Events:
        cfg, ev = self.config, Events()
        for t in self.tracks:
            self._predict(t, stamp_ns)
        high = [o for o in observations if o.score >= cfg.high_score]
        low = [o for o in observations if cfg.low_score <= o.score < cfg.high_score]
        pairs, left, new = self._match(self.tracks, high)
        for i, j in pairs:
            self._hit(self.tracks[i], high[j], stamp_ns, ev)
        remaining = [self.tracks[i] for i in left]
        pairs_low, _, _ = self._match(remaining, low)
        for i, j in pairs_low:
            self._hit(remaining[i], low[j], stamp_ns, ev)
        new = self._reacquire([high[j] for j in new], stamp_ns, ev)
        for o in new:
            if self._may_start(o):
                self._start(o, stamp_ns, ev)
        self._expire(stamp_ns, ev)
        return ev

    def _may_start(self, o: Observation) -> bool:
        """Plausible (whole, its class's size), precise enough, and explained by no known track of
        its class (live, just started or lost): not within its Mahalanobis gate, nor within
        birth_spacing_m of it, nor within 3 sigma of the detection's widest horizontal axis
        (placements at 10-20 m are biased by 1-2 m beyond their covariance, and a far one 2-5 m
        sideways as well as along its line of sight, while a track seen many times is placed to
        0.1 m: by Mahalanobis alone such a view of a known object reads as a second one; seen
        nearer, a real second object is placed precisely enough to start)."""
        if not self._plausible(o) or self._imprecise(o):
            return False
        known = [t for t in self.tracks + self.lost if t.class_id == o.class_id]
        if not known:
            return True
        diff, d2 = self._differences(known, [o])
        spacing = max(self.config.birth_spacing_m, 3.0 * _horizontal_sigma(o.measurement.covariance_m2))
        return bool((d2 > CHI2_3DOF_99).all() and (np.linalg.norm(diff[..., :2], axis=2) > spacing).all())

    def _reacquire(self, obs: list[Observation], stamp_ns: int, ev: Events) -> list[Observation]:
        """Match what would start new tracks against lost ones first: an object the vehicle comes
        back to (the next leg of a search) keeps its track id instead of becoming a duplicate.
        Lost tracks stand where they were last seen, with the covariance they had then (a static
        object; one that moved away while unseen becomes a new track). Returns the observations
        left to start tracks."""
        self._forget(stamp_ns)
        if not self.lost or not obs:
            return obs
        pairs, _, rest = self._match(self.lost, obs)
        for i, j in pairs:
            t = self.lost[i]
            t.stamp_ns = stamp_ns
            self.tracks.append(t)
            self._hit(t, obs[j], stamp_ns, ev)
            ev.reacquired.append(t)
        revived = {id(self.lost[i]) for i, _ in pairs}
        self.lost = [t for t in self.lost if id(t) not in revived]
        return [obs[j] for j in rest]

    def expire(self, stamp_ns: int) -> Events:
        """Delete tracks unseen for their timeout at `stamp_ns` (also while no frame comes)."""
        ev = Events()
        self._expire(stamp_ns, ev)
        return ev

    def _plausible(self, o: Observation) -> bool:
        """Not cut by the image's edge, and a box between partial_scale and crowd_scale times what
        its class's typical size fills from there (0: unknown): shorter is a partial view (a car
        going under an awning: its boxes shrink frame by frame, their centres with them), taller
        takes in a neighbour."""
        return not o.cut and (o.box_scale <= 0 or self.config.partial_scale <= o.box_scale <= self.config.crowd_scale)

    def _imprecise(self, o: Observation, t: Track | None = None) -> bool:
        """Placed less precisely than birth_sigma_m (horizontal 1 sigma) -- and than twice the
        track `t` is placed: far, where a placement's error is mostly bias (a few metres at 35-45
        m), not noise that averages out; a track born far still learns from its peers."""
        sigma = _horizontal_sigma(o.measurement.covariance_m2)
        return sigma > self.config.birth_sigma_m and (t is None or sigma > 2 * _horizontal_sigma(t.P))

    def _hit(self, t: Track, o: Observation, stamp_ns: int, ev: Events) -> None:
        """A detection joins the track: it always keeps it alive; it moves it only when it is
        precise (a far one would drag a track placed from near metres away, frame by frame, onto a
        neighbour) and a whole view (_whole)."""
        whole_scale = statistics.median(t.scales) if len(t.scales) >= 3 else 0.0
        if not self._imprecise(o, t) and self._whole(t, o):
            self._correct(t, self._widened(o, whole_scale))
            t.seen_x, t.seen_P, t.seen_ns = t.x[:3].copy(), t.P[:3, :3].copy(), stamp_ns
        t.hits += 1
        t.last_seen_ns = stamp_ns
        t.best_score = max(t.best_score, o.score)
        t.range_m = o.measurement.range_m
        if not t.confirmed and t.hits >= self.config.confirm_hits and self._fits_class(t):
            t.confirmed = True
            ev.confirmed.append(t)

    def _widened(self, o: Observation, whole_scale: float) -> Measurement:
        """The placement, less certain when its box is shorter than the track's whole boxes (median
        box_scale `whole_scale`; 0: none yet): a box a fraction r of them may show only part of the
        object -- the detector boxing a truck's cab as it nears it end-on, the box shrinking frame by
        frame before partial_ratio calls it partial -- so its centre may lie off the object's by the
        part it lacks: 1 sigma (1 - r) times the class's length (times partial_sigma_scale),
        horizontally, either way. A whole view keeps its covariance; so does association (gates)."""
        m, k = o.measurement, self.config.partial_sigma_scale
        if k <= 0 or whole_scale <= 0 or not 0 < o.box_scale < whole_scale:
            return m
        sigma = k * (1.0 - o.box_scale / whole_scale) * o.length_m
        return Measurement(m.position_m, m.covariance_m2 + HORIZONTAL * sigma ** 2, m.range_m, m.method)

    def _fits_class(self, t: Track) -> bool:
        """Whether the track's whole boxes show an object of its class's size: at least half of
        them (since it started) fill confirm_scale of what its class's typical size fills. The
        detector boxes a whole object at 1.10-1.31x that (each class's median, every range of the
        village search); a look-alike of another size that it boxes as the class -- a 1.8 m wall,
        10 m long, seen obliquely as a 3.4 m truck: 0.71-0.96x -- stays tentative however often it
        is seen (it still holds its place: no second track starts on it). Boxes cut by the image's
        edge, partial and crowded views never count (_whole); a track with none yet is not judged.
        All its boxes, not the last few: a look-alike's run of near-fitting views must not outvote
        the many before it."""
        return 2 * t.fitting_views >= t.whole_views

    def _count_whole(self, t: Track, scale: float) -> None:
        t.whole_views += 1
        t.fitting_views += scale >= self.config.confirm_scale

    def _whole(self, t: Track, o: Observation) -> bool:
        """Whether the box shows the whole object: its box_scale against the median of the track's
        last whole boxes (`partial_ratio`; the first three are taken as they come). A much shorter
        box is a partial view (the object half hidden behind something nearer, or cut by the
        image's edge), a much taller one takes in a neighbour: its centre is not the object's, so it
        keeps the track alive without moving it; so does a box cut by the image's edge. Five partial
        views in a row: the object looks different now (it sat down, turned), its boxes are learnt
        anew -- from plausible boxes only (_plausible: an implausible one is never whole), and a
        shorter look only from boxes its class's whole size fills (confirm_scale): a run of boxes
        smaller than that is still a part of it. Near the village's truck end-on (13-21 m) the
        detector boxes its cab alone (box_scale 0.75-0.93, 1.0-1.4 from 23-32 m), placed 1.5-2.7 m
        short: learnt as its new look after five, forty such views dragged the track 2.3 m short."""
        if not self._plausible(o):
            return False
        if o.box_scale <= 0:
            return True
        scales = t.scales
        if len(scales) >= 3 and (t.partial_run < 5 or o.box_scale < self.config.confirm_scale) and not (
                1 / self.config.partial_ratio <= o.box_scale / statistics.median(scales) <= self.config.partial_ratio):
            t.partial_run += 1
            return False
        if t.partial_run >= 5:
            scales.clear()
        t.partial_run = 0
        scales.append(o.box_scale)
        self._count_whole(t, o.box_scale)
        del scales[:-9]
        return True

    def _start(self, o: Observation, stamp_ns: int, ev: Events) -> None:
        p = np.zeros((6, 6))
        p[:3, :3] = o.measurement.covariance_m2
        p[3:, 3:] = HORIZONTAL * self.config.initial_speed_mps ** 2
        t = Track(self.next_id, o.class_id, o.class_name, np.concatenate([o.measurement.position_m, np.zeros(3)]), p,
                  stamp_ns, stamp_ns, stamp_ns, best_score=o.score, range_m=o.measurement.range_m,
                  seen_ns=stamp_ns, scales=[o.box_scale] if o.box_scale > 0 else [])
        self.next_id += 1
        if o.box_scale > 0:
            self._count_whole(t, o.box_scale)
        t.seen_x, t.seen_P = t.x[:3].copy(), t.P[:3, :3].copy()
        self.tracks.append(t)
        if self.config.confirm_hits <= 1 and self._fits_class(t):
            t.confirmed = True
            ev.confirmed.append(t)

    def _expire(self, stamp_ns: int, ev: Events) -> None:
        keep = []
        for t in self.tracks:
            unseen_s = (stamp_ns - t.last_seen_ns) * 1e-9
            if t.confirmed and unseen_s > self.config.lost_timeout_s:
                ev.lost.append(t)
                self._remember(t)
                self.lost.append(t)
            elif not t.confirmed and unseen_s > self.config.tentative_timeout_s:
                pass                            # never confirmed: dropped without an event
            else:
                keep.append(t)
        self.tracks = keep
        self._forget(stamp_ns)

    def _remember(self, t: Track) -> None:
        """A lost track, as it was just after its last hit, standing still."""
        t.x = np.concatenate([t.seen_x, np.zeros(3)])
        p = np.zeros((6, 6))
        p[:3, :3] = t.seen_P
        p[3:, 3:] = HORIZONTAL * self.config.initial_speed_mps ** 2
        t.P = p

    def _forget(self, stamp_ns: int) -> None:
        self.lost = [t for t in self.lost if (stamp_ns - t.last_seen_ns) * 1e-9 <= self.config.forget_s]
