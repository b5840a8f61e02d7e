"""The LiDAR's ray cast and returns, compiled with numba: per triangle, only the rays of the sweep
that can hit it; then, in one pass, the rays in range as points and labels.

The sweep is a grid of rays (beam elevation x azimuth step, lidar.py) from one origin. The rays
that pass through a triangle V0 V1 V2 (sensor-frame vertices relative to the origin) are those
r = a V0 + b V1 + c V2 with a, b, c >= 0; their azimuths are the azimuths of the triangle's
projection on the sensor's xy plane seen from the origin (scaling by a positive factor keeps the
azimuth), so a triangle whose projection does not contain the origin spans the azimuth interval of
its vertices (< 180°); one that does contains the sensor's up or down axis and spans all azimuths.
Elevation is extreme on the triangle's edges or at that axis; along an edge its tangent z / rho has
one stationary point, found in closed form. Each ray inside those bounds (plus one cell of margin)
gets the camera rasteriser's exact test: the edge functions E_k(r) = (V_k+1 x V_k+2) . r all have
the sign of D = det(V0, V1, V2), and the hit is at t = D / (E_0 + E_1 + E_2). Back faces of a
closed convex part (triangles facing outward) are skipped while the origin is outside that part:
a ray reaches them only through one of its front faces. Single-threaded on purpose: the stack
shares two cores.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .lidar import LABEL_GROUND, LABEL_OBSTACLE, LABEL_OVERHEAD

TWO_PI = 2.0 * math.pi


@nb.njit(cache=True, nogil=True)
def _edge_elevations(a, b, lo_hi):
    """Widen lo_hi (min, max elevation, rad) by the edge a -> b (sensor-frame points)."""
    dx, dy, dz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    pd = a[0] * dx + a[1] * dy
    dd = dx * dx + dy * dy
    pp = a[0] * a[0] + a[1] * a[1]
    den = dz * pd - a[2] * dd
    for k in range(3):
        if k == 0:
            s = 0.0
        elif k == 1:
            s = 1.0
        else:   # where d/ds (z / rho) = 0: linear in s
            if den == 0.0:
                continue
            s = (a[2] * pd - dz * pp) / den
            if not 0.0 < s < 1.0:
                continue
        x, y, z = a[0] + s * dx, a[1] + s * dy, a[2] + s * dz
        el = math.atan2(z, math.sqrt(x * x + y * y))
        lo_hi[0] = min(lo_hi[0], el)
        lo_hi[1] = max(lo_hi[1], el)


@nb.njit(cache=True, nogil=True)
def _det(vs, tri):
    v0, v1, v2 = vs[tri[0]], vs[tri[1]], vs[tri[2]]
    return (v0[0] * (v1[1] * v2[2] - v1[2] * v2[1]) - v0[1] * (v1[0] * v2[2] - v1[2] * v2[0])
            + v0[2] * (v1[0] * v2[1] - v1[1] * v2[0]))


@nb.njit(cache=True, nogil=True)
def cast_sweep(vs, tris, tri_plane, tri_part, part_closed, dx, dy, dz, beams, steps, el0, el_step, t_hit, plane,
               sky):
    """Nearest hit of every ray of the sweep: t_hit (N,) float64 (inf: nothing) and plane (N,)
    int32 (`sky`: nothing). vs: (V, 3) float64 sensor-frame vertices relative to the origin;
    tris: (T, 3) vertex indices; tri_plane: (T,) plane id per triangle; tri_part: (T,) part id,
    part_closed[part]: a closed convex part with outward-facing triangles; dx, dy, dz: (N,) unit
    directions, N = beams * steps, row-major (beam, azimuth step); beam b is at elevation
    el0 + b * el_step (rad), step c at azimuth 2 pi c / steps."""
    t_hit[:] = np.inf
    plane[:] = sky
    lo_hi = np.empty(2)
    e = np.empty((3, 3))
    az_scale = steps / TWO_PI
    outside = np.zeros(part_closed.shape[0], np.bool_)   # the origin is in front of one of its faces
    for t in range(tris.shape[0]):
        if _det(vs, tris[t]) < 0.0:
            outside[tri_part[t]] = True
    for t in range(tris.shape[0]):
        v0, v1, v2 = vs[tris[t, 0]], vs[tris[t, 1]], vs[tris[t, 2]]
        det = _det(vs, tris[t])
        if det == 0.0:
            continue   # the plane contains the origin: seen edge-on, hit by no ray
        if det > 0.0 and part_closed[tri_part[t]] and outside[tri_part[t]]:
            continue   # a back face of a convex part seen from outside: its front face is nearer
        sgn = 1.0 if det > 0.0 else -1.0
        for k in range(3):   # edge functions, scaled so inside is >= 0
            a, b = vs[tris[t, (k + 1) % 3]], vs[tris[t, (k + 2) % 3]]
            e[k, 0] = sgn * (a[1] * b[2] - a[2] * b[1])
            e[k, 1] = sgn * (a[2] * b[0] - a[0] * b[2])
            e[k, 2] = sgn * (a[0] * b[1] - a[1] * b[0])
        # Does the triangle's projection on the xy plane contain the origin (the up/down axis)?
        c0 = v0[0] * v1[1] - v0[1] * v1[0]
        c1 = v1[0] * v2[1] - v1[1] * v2[0]
        c2 = v2[0] * v0[1] - v2[1] * v0[0]
        around_axis = (c0 >= 0.0 and c1 >= 0.0 and c2 >= 0.0) or (c0 <= 0.0 and c1 <= 0.0 and c2 <= 0.0)
        lo_hi[0], lo_hi[1] = np.inf, -np.inf
        _edge_elevations(v0, v1, lo_hi)
        _edge_elevations(v1, v2, lo_hi)
        _edge_elevations(v2, v0, lo_hi)
        if around_axis:
            if e[0, 2] >= 0.0 and e[1, 2] >= 0.0 and e[2, 2] >= 0.0:
                lo_hi[1] = 0.5 * math.pi      # the up axis passes through it
            if e[0, 2] <= 0.0 and e[1, 2] <= 0.0 and e[2, 2] <= 0.0:
                lo_hi[0] = -0.5 * math.pi     # the down axis
            col_lo, col_hi = 0, steps - 1
        else:   # azimuths of the vertices, unwrapped around the first one (span < pi)
            a0 = math.atan2(v0[1], v0[0])
            amin = amax = a0
            for k in (1, 2):
                d = math.atan2(vs[tris[t, k], 1], vs[tris[t, k], 0]) - a0
                d -= TWO_PI * math.floor((d + math.pi) / TWO_PI)
                amin, amax = min(amin, a0 + d), max(amax, a0 + d)
            col_lo = int(math.floor(amin * az_scale)) - 1
            col_hi = int(math.ceil(amax * az_scale)) + 1
            if col_hi - col_lo >= steps:
                col_lo, col_hi = 0, steps - 1
        b_lo = max(0, int(math.floor((lo_hi[0] - el0) / el_step)) - 1)
        b_hi = min(beams - 1, int(math.ceil((lo_hi[1] - el0) / el_step)) + 1)
        pid = tri_plane[t]
        for bm in range(b_lo, b_hi + 1):
            row = bm * steps
            for cc in range(col_lo, col_hi + 1):
                i = row + (cc % steps)
                rx, ry, rz = dx[i], dy[i], dz[i]
                s0 = e[0, 0] * rx + e[0, 1] * ry + e[0, 2] * rz
                if s0 < 0.0:
                    continue
                s1 = e[1, 0] * rx + e[1, 1] * ry + e[1, 2] * rz
                if s1 < 0.0:
                    continue
                s2 = e[2, 0] * rx + e[2, 1] * ry + e[2, 2] * rz
                if s2 < 0.0:
                    continue
                den = s0 + s1 + s2
                if den <= 0.0:
                    continue
                th = abs(det) / den
                if th < t_hit[i]:
                    t_hit[i] = th
                    plane[i] = pid


@nb.njit(cache=True, nogil=True)
def sweep_returns(t, plane, noise, std, min_r, max_r, gate_lo, gate_hi, dx, dy, dz, up, z0, z_overhead,
                  plane_ground, points, labels):
    """The sweep's returns: rays whose range t (+ noise * std when `noise` is not empty) lies in
    [min_r, max_r], in ray order: points (N, 3) float32 in the sensor frame and labels (ground,
    obstacle, or overhead when the hit's world z = z0 + t (up . d) is above z_overhead). Only rays
    with t in [gate_lo, gate_hi] can return; they take the noise samples in ray order (noise holds
    one per such ray). Float32 arithmetic in numpy's order, so the result is the vectorised one's
    bit for bit. Returns N."""
    n = 0
    j = 0
    noisy = noise.size > 0
    for i in range(t.size):
        if t[i] < gate_lo or t[i] > gate_hi:
            continue
        r = t[i]
        if noisy:
            r = t[i] + noise[j] * std
            j += 1
        if r < min_r or r > max_r:
            continue
        points[n, 0] = dx[i] * r
        points[n, 1] = dy[i] * r
        points[n, 2] = dz[i] * r
        if plane_ground[plane[i]]:
            labels[n] = LABEL_GROUND
        else:
            hit_z = z0 + t[i] * (up[0] * dx[i] + up[1] * dy[i] + up[2] * dz[i])
            labels[n] = LABEL_OVERHEAD if hit_z > z_overhead else LABEL_OBSTACLE
        n += 1
    return n
