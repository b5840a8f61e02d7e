"""Per-pixel camera kernels, compiled with numba: which surface each pixel sees, and its colour.

`rasterize` is a z-buffer over the scene's triangles. A pixel's ray r = (x, y, 1) (optical
frame, x = (u - cx) / fx at the pixel centre) passes through triangle V0 V1 V2 (camera-relative
vertices) in front of the camera iff r = a V0 + b V1 + c V2 with a, b, c >= 0, i.e. iff the three
edge functions E_k(r) = (V_k+1 x V_k+2) . r all have the sign of D = det(V0, V1, V2). Each E_k is
affine in the pixel coordinates, and so is 1/z = (E_0 + E_1 + E_2) / D on the triangle's plane, so
coverage and depth are exact per pixel centre -- the same hit a ray cast would find -- and a
triangle partly behind the camera needs no clipping (only its bounding box is taken from the part
with z > 0). Single-threaded on purpose: the whole stack shares two cores.

`shade` turns (plane id, 1/z) per pixel into the image: world-anchored texture coordinates from
the plane's axes, a mip level from the pixel's footprint on the surface, one texel, times the
plane's lit colour. It serves both the rasterised and the ray-cast (reference) visibility.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..world.scene import TEXTURE_SIZE

Z_NEAR_M = 1e-6   # bounding boxes use the part of a triangle in front of this (no hit is nearer)

# Columns of the per-frame plane table `shade` reads (camera frame, texel units).
COL_S0, COL_T0, COL_E1, COL_E2, COL_N, COL_LOD = 0, 1, 2, 5, 8, 11
PLANE_COLS = 12


def plane_table(scene, r_wc: np.ndarray, o: np.ndarray, fx: float) -> np.ndarray:
    """Per-plane constants `shade` reads for a camera at this pose (rotation r_wc, origin o, ENU;
    focal length fx px): camera frame, texel units, one row per plane plus the sky row."""
    inv = scene.plane_inv_texel
    tab = np.empty((scene.num_planes + 1, PLANE_COLS))
    # Texture coordinate of the camera origin, wrapped to one tile (mips wrap consistently)
    # so the per-pixel offsets added to it stay small.
    tab[:, COL_S0] = np.mod((scene.plane_e1 @ o + scene.plane_tex_offset_m[:, 0]) * inv, TEXTURE_SIZE)
    tab[:, COL_T0] = np.mod((scene.plane_e2 @ o + scene.plane_tex_offset_m[:, 1]) * inv, TEXTURE_SIZE)
    tab[:, COL_E1:COL_E1 + 3] = (scene.plane_e1 @ r_wc) * inv[:, None]
    tab[:, COL_E2:COL_E2 + 3] = (scene.plane_e2 @ r_wc) * inv[:, None]
    tab[:, COL_N:COL_N + 3] = scene.plane_normal @ r_wc
    tab[:, COL_LOD] = inv / fx
    return tab


@nb.njit(cache=True, nogil=True)
def rasterize(vc, tris, tri_plane, fx, fy, cx, cy, inv_z, plane, sky):
    """Fill inv_z (H, W) float64 with 1/z of the nearest surface (0: nothing) and plane (H, W)
    int16 or int32 with its plane id (`sky` where nothing). vc: (V, 3) float64 camera-frame vertices;
    tris: (T, 3) vertex indices; tri_plane: (T,) plane id per triangle."""
    h, w = plane.shape
    inv_z[:] = 0.0
    plane[:] = sky
    ea, eb, ed = np.empty(3), np.empty(3), np.empty(3)
    for t in range(tris.shape[0]):
        v0, v1, v2 = vc[tris[t, 0]], vc[tris[t, 1]], vc[tris[t, 2]]
        if v0[2] < Z_NEAR_M and v1[2] < Z_NEAR_M and v2[2] < Z_NEAR_M:
            continue
        # Screen bounding box of the part of the triangle with z >= Z_NEAR_M.
        umin, umax, vmin, vmax = 1e30, -1e30, 1e30, -1e30
        for k in range(3):
            p, q = vc[tris[t, k]], vc[tris[t, (k + 1) % 3]]
            for m in range(2):
                if m == 0:
                    if p[2] < Z_NEAR_M:
                        continue
                    x, y, z = p[0], p[1], p[2]
                else:   # where edge p-q crosses z = Z_NEAR_M
                    if (p[2] < Z_NEAR_M) == (q[2] < Z_NEAR_M):
                        continue
                    f = (Z_NEAR_M - p[2]) / (q[2] - p[2])
                    x, y, z = p[0] + f * (q[0] - p[0]), p[1] + f * (q[1] - p[1]), Z_NEAR_M
                pu, pv = fx * x / z + cx, fy * y / z + cy
                umin, umax = min(umin, pu), max(umax, pu)
                vmin, vmax = min(vmin, pv), max(vmax, pv)
        r0 = max(0.0, np.ceil(vmin) - 1.0)
        r1 = min(h - 1.0, np.floor(vmax) + 1.0)
        c0 = max(0.0, np.ceil(umin) - 1.0)
        c1 = min(w - 1.0, np.floor(umax) + 1.0)
        if r0 > r1 or c0 > c1:
            continue
        # Edge functions (scaled so inside is >= 0) and 1/z as affine functions of (u, v).
        det = (v0[0] * (v1[1] * v2[2] - v1[2] * v2[1]) - v0[1] * (v1[0] * v2[2] - v1[2] * v2[0])
               + v0[2] * (v1[0] * v2[1] - v1[1] * v2[0]))
        if det == 0.0:
            continue   # the plane contains the camera centre: seen edge-on, covers no pixel
        sgn = 1.0 if det > 0.0 else -1.0
        for k in range(3):
            a, b = vc[tris[t, (k + 1) % 3]], vc[tris[t, (k + 2) % 3]]
            nx = a[1] * b[2] - a[2] * b[1]
            ny = a[2] * b[0] - a[0] * b[2]
            nz = a[0] * b[1] - a[1] * b[0]
            ea[k] = sgn * nx / fx
            eb[k] = sgn * ny / fy
            ed[k] = sgn * (nz - nx * cx / fx - ny * cy / fy)
        inv_d = 1.0 / abs(det)
        za, zb, zd = ((ea[0] + ea[1] + ea[2]) * inv_d, (eb[0] + eb[1] + eb[2]) * inv_d,
                      (ed[0] + ed[1] + ed[2]) * inv_d)
        pid = tri_plane[t]
        for row in range(int(r0), int(r1) + 1):
            lo, hi = c0, c1
            for k in range(3):   # the span of this row where E_k = ea u + (eb v + ed) >= 0
                e0 = eb[k] * row + ed[k]
                if ea[k] > 0.0:
                    lo = max(lo, np.ceil(-e0 / ea[k]))
                elif ea[k] < 0.0:
                    hi = min(hi, np.floor(-e0 / ea[k]))
                elif e0 < 0.0:
                    hi = -1.0
            if lo > hi:
                continue
            zr = zb * row + zd
            for col in range(int(lo), int(hi) + 1):
                iz = za * col + zr
                if iz > inv_z[row, col]:
                    inv_z[row, col] = iz
                    plane[row, col] = pid


@nb.njit(cache=True, nogil=True)
def shade(inv_z, plane, fx, fy, cx, cy, tab, plane_tex, level_off, level_min_fp, texels, tex_log2,
          colours, image, depth, entity, plane_entity):
    """Colour every pixel from its plane id and 1/z (see the module docstring).

    tab: (P + 1, PLANE_COLS) float64 per-plane table for this pose (texel units; row P = sky).
    level_min_fp[L]: the smallest pixel footprint (texels) that selects mip level L.
    colours: (P + 1, C) uint8 lit colours; image: (H, W, C) uint8 out. depth (H, W) float32 and
    entity (H, W) int32 are filled when non-empty (truth layers)."""
    h, w = plane.shape
    n_ch = colours.shape[1]
    sky = colours.shape[0] - 1
    layers = depth.size > 0
    full = (1 << tex_log2) - 1
    levels = level_min_fp.shape[0]
    for row in range(h):
        y = (row - cy) * (1.0 / fy)
        for col in range(w):
            p = plane[row, col]
            x = (col - cx) * (1.0 / fx)
            if p >= sky:   # sky: texel 0 of the flat texture (255) over the sky colour
                z = np.inf
                tex = texels[plane_tex[sky]]
            else:
                z = 1.0 / inv_z[row, col]
                s = tab[p, COL_S0] + z * (tab[p, COL_E1] * x + tab[p, COL_E1 + 1] * y + tab[p, COL_E1 + 2])
                t = tab[p, COL_T0] + z * (tab[p, COL_E2] * x + tab[p, COL_E2 + 1] * y + tab[p, COL_E2 + 2])
                # Footprint of the pixel on the surface in texels: z / fx / cos(incidence) / texel.
                # (z * lod / max(cos, 1e-6) as a fraction: one division fewer per pixel.)
                nd = abs(tab[p, COL_N] * x + tab[p, COL_N + 1] * y + tab[p, COL_N + 2])
                rn = math.sqrt(x * x + y * y + 1.0)   # cos = nd / rn
                fp_num, fp_den = z * tab[p, COL_LOD] * rn, max(nd, 1e-6 * rn)
                lvl = 0
                while lvl + 1 < levels and fp_num >= level_min_fp[lvl + 1] * fp_den:
                    lvl += 1
                mask = full >> lvl
                si = (int(math.floor(s)) >> lvl) & mask
                ti = (int(math.floor(t)) >> lvl) & mask
                tex = texels[plane_tex[p] + level_off[lvl] + (ti << (tex_log2 - lvl)) + si]
            if n_ch == 3:   # unrolled for RGB: ~8 % of the kernel's CPU (the loop's trip count is not known)
                image[row, col, 0] = (np.int32(colours[p, 0]) * np.int32(tex) + 128) >> 8
                image[row, col, 1] = (np.int32(colours[p, 1]) * np.int32(tex) + 128) >> 8
                image[row, col, 2] = (np.int32(colours[p, 2]) * np.int32(tex) + 128) >> 8
            else:
                for c in range(n_ch):
                    image[row, col, c] = (np.int32(colours[p, c]) * np.int32(tex) + 128) >> 8
            if layers:
                depth[row, col] = z
                entity[row, col] = plane_entity[p]
