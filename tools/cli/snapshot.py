"""`aero snapshot`: save one stereo pair and one LiDAR scan from a running stack, for a look.

Subscribes to sensors/camera/{left,right}/image and sensors/lidar/points (plus
sim/truth/lidar_labels when the simulator publishes it), waits (bounded by --timeout) for a
left/right pair with the same stamp and one scan, and writes left.png, right.png and scan.ply
(binary PLY; with a per-point `label` property -- 0 ground, 1 obstacle, 2 overhead -- when the
sim's labels for that scan arrived). Prints each file with its stamp. Exit 2 with one line when
something did not arrive.
"""
from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from aeroperception.schemas import Image, PointCloud, SchemaError, decode

from aeroperception.tools.common import CliError, add_session_arguments, full_key, open_client

LEFT, RIGHT = "sensors/camera/left/image", "sensors/camera/right/image"
POINTS, LABELS = "sensors/lidar/points", "sim/truth/lidar_labels"
LABELS_GRACE_S = 0.5   # after a scan, how long to wait for the sim's labels of the same stamp
# sim.sensors.lidar.LABEL_NAMES, repeated so the CLI does not import Open3D (2.5 s) for three words
LABEL_NAMES = ("ground", "obstacle", "overhead")
_KEEP = 8              # recent messages kept per key while looking for matching stamps


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("snapshot", help="save a stereo image pair (PNG) and a LiDAR scan (PLY)")
    add_session_arguments(p)
    p.add_argument("--out", default="snapshot", metavar="DIR", help="output folder (default ./snapshot)")
    p.add_argument("--timeout", type=float, default=5.0, metavar="S",
                   help="seconds to wait for the images and the scan (default 5)")
    p.set_defaults(func=run)


class _Collector:
    """The latest few decoded messages per key; signals when a matching set is complete."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.msgs: dict[str, dict[int, object]] = {k: {} for k in (LEFT, RIGHT, POINTS, LABELS)}
        self.bad: dict[str, str] = {}
        self.points_at = 0.0   # monotonic time the first scan arrived

    def callback(self, key: str, cls: type):
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                msg = decode(sample.payload.to_bytes(), cls)
            except SchemaError as e:
                with self.cond:
                    self.bad[key] = str(e)
                return
            with self.cond:
                box = self.msgs[key]
                box[msg.header.stamp_ns] = msg
                while len(box) > _KEEP:
                    del box[min(box)]
                if key == POINTS and not self.points_at:
                    self.points_at = time.monotonic()
                self.cond.notify_all()
        return on_sample

    def pair(self) -> tuple[Image, Image] | None:
        """The newest left/right images with equal stamps."""
        common = set(self.msgs[LEFT]) & set(self.msgs[RIGHT])
        if not common:
            return None
        s = max(common)
        return self.msgs[LEFT][s], self.msgs[RIGHT][s]

    def scan(self) -> tuple[PointCloud, PointCloud | None] | None:
        """The newest scan, with its labels if they arrived (same stamp, same point count)."""
        pts = self.msgs[POINTS]
        if not pts:
            return None
        for s in sorted(pts, reverse=True):
            lab = self.msgs[LABELS].get(s)
            if lab is not None and lab.labels is not None and lab.labels.shape[0] == pts[s].points.shape[0]:
                return pts[s], lab
        return pts[max(pts)], None

    def complete(self) -> bool:
        if self.pair() is None:
            return False
        scan = self.scan()
        if scan is None:
            return False
        # Labels come from the sim right after the scan; a real driver has none: do not wait long.
        return scan[1] is not None or time.monotonic() - self.points_at > LABELS_GRACE_S


def png_pixels(img: Image) -> np.ndarray:
    """What save_png writes: RGB (H, W, 3) or mono (H, W) uint8/uint16 for any Image encoding."""
    a = img.to_numpy()
    enc = img.encoding
    if enc in ("bgr8", "bgra8"):
        a = a[..., 2::-1]
    elif enc == "rgba8":
        a = a[..., :3]
    elif enc == "32FC1":   # depth: scale the finite range to 8 bits, nothing hit -> 0
        f = np.asarray(a, dtype=np.float32).reshape(a.shape[:2])
        ok = np.isfinite(f)
        lo, hi = (float(f[ok].min()), float(f[ok].max())) if ok.any() else (0.0, 1.0)
        a = np.where(ok, (f - lo) / max(hi - lo, 1e-9) * 254 + 1, 0).astype(np.uint8)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    return np.ascontiguousarray(a)


def _stamp(ns: int) -> str:
    return f"stamp {ns / 1e9:.6f} s ({ns} ns)"


def run(args) -> int:
    from aeroperception.services.sim.sensors.export import save_ply, save_png

    out = Path(args.out)
    col = _Collector()
    session = open_client(args)
    subs = [session.declare_subscriber(full_key(args, k), col.callback(k, cls))
            for k, cls in ((LEFT, Image), (RIGHT, Image), (POINTS, PointCloud), (LABELS, PointCloud))]
    try:
        deadline = time.monotonic() + max(args.timeout, 0.0)
        with col.cond:
            while not col.complete():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                col.cond.wait(min(left, 0.1))
            pair, scan, bad = col.pair(), col.scan(), dict(col.bad)
            have = {k: bool(v) for k, v in col.msgs.items()}
    finally:
        for s in subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - best effort on the way out
                pass
        session.close()

    if pair is None and not have[LEFT] and not have[POINTS]:
        raise CliError(_missing(args, LEFT, "images", bad)
                       + (": is the sim running with --sensors all?" if LEFT not in bad else ""))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CliError(f"cannot create {out}: {e.strerror or e}") from None

    lines: list[str] = []
    try:
        if pair is not None:
            for name, img in (("left.png", pair[0]), ("right.png", pair[1])):
                save_png(out / name, png_pixels(img))
                lines.append(f"{out / name}  {img.width}x{img.height} {img.encoding}  {_stamp(img.header.stamp_ns)}")
        if scan is not None:
            pts, lab = scan
            labels = lab.labels.to_numpy() if lab is not None else None
            save_ply(out / "scan.ply", pts.points.to_numpy(), labels)
            what = f"{pts.points.shape[0]} points, frame {pts.header.frame_id or '?'}"
            if labels is not None:
                counts = np.bincount(labels, minlength=len(LABEL_NAMES))
                what += ", labels " + " ".join(
                    f"{LABEL_NAMES[i] if i < len(LABEL_NAMES) else i}={int(n)}" for i, n in enumerate(counts) if n)
            lines.append(f"{out / 'scan.ply'}  {what}  {_stamp(pts.header.stamp_ns)}")
    except OSError as e:
        raise CliError(f"cannot write into {out}: {e}") from None
    for line in lines:
        print(line, flush=True)

    missing = []
    if pair is None:
        if not have[LEFT]:
            missing.append(_missing(args, LEFT, "images", bad))
        elif not have[RIGHT]:
            missing.append(_missing(args, RIGHT, "images", bad))
        else:
            missing.append(f"no left/right images with equal stamps within {args.timeout:g} s")
    if scan is None:
        missing.append(_missing(args, POINTS, "scans", bad))
    if missing:
        raise CliError("; ".join(missing))
    return 0


def _missing(args, key: str, what: str, bad: dict[str, str]) -> str:
    if key in bad:
        return f"{key}: payloads do not decode ({bad[key]})"
    return f"no {what} on {full_key(args, key)} within {args.timeout:g} s"
