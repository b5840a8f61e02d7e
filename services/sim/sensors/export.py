"""Snapshot writers for debugging and docs: PNG images and PLY point clouds (no Open3D needed,
so a snapshot can be taken anywhere the sim runs and opened in any viewer)."""
from __future__ import annotations

import os

import cv2
import numpy as np


def save_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an RGB (H, W, 3) or mono (H, W) uint8 image."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"cannot write {path}")


def save_ply(path: str | os.PathLike, points: np.ndarray, labels: np.ndarray | None = None,
             binary: bool = True) -> None:
    """Write (N, 3) points (float32 x, y, z) and optional per-point uint8 labels as PLY."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if labels is not None:
        fields.append(("label", "u1"))
    rec = np.empty(len(pts), dtype=fields)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if labels is not None:
        rec["label"] = np.asarray(labels, dtype=np.uint8).reshape(-1)
    props = "".join(f"property {'float' if t == '<f4' else 'uchar'} {n}\n" for n, t in fields)
    fmt = "binary_little_endian" if binary else "ascii"
    header = f"ply\nformat {fmt} 1.0\nelement vertex {len(pts)}\n{props}end_header\n"
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            f.write(rec.tobytes())
        else:
            for row in rec:
                f.write((" ".join(str(v) for v in row.tolist()) + "\n").encode("ascii"))
