"""Raycasting scene built from a Scenario: geometry, per-plane materials and procedural textures.

The world is static, so everything is built once per scenario (`get_scene` caches it): one
Open3D RaycastingScene holding every triangle, plus per-triangle -> plane tables. All shapes are
convex and flat-faced, so shading is per *plane* (a face of a part): its normal, lambert shade,
material colour, texture and texture axes are constants the renderers look up by plane id.

Textures are procedural but precomputed: a few 1024x1024 tiles (value noise + blobs for
"natural" surfaces, rectangles for "urban" ones, rich in corners for KLT) with mipmaps, addressed
by world-anchored plane coordinates, so the same surface point looks the same from every camera
and the pattern never swims. Frames: ENU metres.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from .scenario import MATERIALS, BoxObject, PoleObject, Scenario, Target, TreeObject

KIND_GROUND, KIND_OBJECT, KIND_TARGET = 0, 1, 2

TEXTURE_SIZE = 1024          # texels per tile side (power of two: wraps with a bit mask)
TEXTURE_LOG2 = 10
TEXTURE_LEVELS = 8           # mip levels 1024 .. 8
TEXTURE_FAMILIES = ("flat", "natural", "urban")
MISS_DEPTH_M = 1.0e6         # depth given to rays that hit nothing (keeps the maths finite)


@dataclass(frozen=True)
class Entity:
    """One thing in the world: the ground, a scenario object or a detector target."""
    kind: int
    index: int               # index into scenario.objects / scenario.targets (-1 for ground)
    class_name: str = ""     # COCO class for targets
    name: str = ""


@dataclass(frozen=True)
class TargetBox:
    """Ground-truth 3D box of a detector target: centre (ENU m), size (l, w, h m), yaw (rad)."""
    entity: int
    target_index: int
    class_name: str
    center_enu_m: np.ndarray
    size_m: tuple[float, float, float]
    yaw_rad: float

    def corners_enu_m(self) -> np.ndarray:
        l, w, h = self.size_m
        sx, sy, sz = np.meshgrid([-0.5, 0.5], [-0.5, 0.5], [-0.5, 0.5], indexing="ij")
        local = np.stack([sx.ravel() * l, sy.ravel() * w, sz.ravel() * h], axis=1)
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return local @ rot.T + self.center_enu_m


# ---------------------------------------------------------------------------------------------
# textures

@dataclass(frozen=True)
class TextureBank:
    """All tiles and their mip levels in one flat uint8 array (one gather per pixel)."""
    texels: np.ndarray               # flat uint8
    family_offset: dict[str, int]    # start of each family's level 0
    level_offset: np.ndarray         # int32 [TEXTURE_LEVELS], relative to a family's start


def _normalise(img: np.ndarray, lo: float, hi: float) -> np.ndarray:
    a, b = np.percentile(img, [1, 99])
    return np.clip(lo + (img - a) * (hi - lo) / (b - a), lo, hi)


def _value_noise(rng: np.random.Generator, cells_amps: list[tuple[int, float]]) -> np.ndarray:
    """Sum of octaves of smoothly interpolated random grids, periodic over the tile."""
    n = TEXTURE_SIZE
    img = np.zeros((n, n), np.float32)
    for cell_px, amp in cells_amps:
        m = n // cell_px
        grid = np.pad(rng.random((m, m)).astype(np.float32), 2, mode="wrap")
        big = cv2.resize(grid, ((m + 4) * cell_px, (m + 4) * cell_px), interpolation=cv2.INTER_CUBIC)
        img += amp * big[2 * cell_px:2 * cell_px + n, 2 * cell_px:2 * cell_px + n]
    return img


def _draw_wrapped(draw, x: int, y: int, reach: int) -> None:
    """Draw a shape at (x, y) and, where it crosses the tile edge, its wrapped copies, so the
    tile repeats without seams."""
    n = TEXTURE_SIZE
    for dx in ((0, -n) if x + reach >= n else (0,)):
        for dy in ((0, -n) if y + reach >= n else (0,)):
            draw(x + dx, y + dy)


def _natural_tile(rng: np.random.Generator) -> np.ndarray:
    """Multi-octave noise plus many small blobs and flecks: grass, dirt, bark-like."""
    img = _value_noise(rng, [(256, 0.6), (64, 0.6), (16, 0.5), (4, 0.25)])
    blobs = np.zeros_like(img)
    n = TEXTURE_SIZE
    for _ in range(6000):
        x, y = (int(v) for v in rng.integers(0, n, 2))
        ax = tuple(int(v) for v in rng.integers(1, 9, 2))
        angle, val = float(rng.uniform(0, 180)), float(rng.uniform(-1.2, 1.2))
        _draw_wrapped(lambda cx, cy: cv2.ellipse(blobs, (cx, cy), ax, angle, 0, 360, val, -1), x, y, 9)
    return _normalise(img + blobs, 45, 255).astype(np.uint8)


def _urban_tile(rng: np.random.Generator) -> np.ndarray:
    """Axis-aligned rectangles (windows, panels, bricks, stains) over fine noise: strong corners."""
    n = TEXTURE_SIZE
    img = _value_noise(rng, [(128, 0.4), (32, 0.3), (4, 0.2)])
    for _ in range(2500):
        x, y = (int(v) for v in rng.integers(0, n, 2))
        w, h = (int(v) for v in rng.integers(3, 48, 2))
        val = float(rng.uniform(-1.0, 1.0))
        thick = -1 if rng.random() < 0.75 else int(rng.integers(1, 3))
        _draw_wrapped(lambda cx, cy: cv2.rectangle(img, (cx, cy), (cx + w, cy + h), val, thick), x, y, 48)
    return _normalise(img, 45, 255).astype(np.uint8)


def _pyr_down_wrapped(tile: np.ndarray) -> np.ndarray:
    """Half-size mip level of a periodic tile (the pyramid filter wraps around the edges)."""
    pad = 4
    return cv2.pyrDown(np.pad(tile, pad, mode="wrap"))[pad // 2:-pad // 2, pad // 2:-pad // 2]


@functools.lru_cache(maxsize=1)
def texture_bank() -> TextureBank:
    """Deterministic (fixed seed) so a scenario renders identically on every machine."""
    rng = np.random.default_rng(20240611)
    tiles = {"flat": np.full((TEXTURE_SIZE, TEXTURE_SIZE), 255, np.uint8),
             "natural": _natural_tile(rng), "urban": _urban_tile(rng)}
    chunks, fam_off, lvl_off, pos = [], {}, [], 0
    for fam in TEXTURE_FAMILIES:
        fam_off[fam] = pos
        level, rel = tiles[fam], 0
        for lvl in range(TEXTURE_LEVELS):
            if fam == TEXTURE_FAMILIES[0]:
                lvl_off.append(rel)
            chunks.append(level.ravel())
            rel += level.size
            pos += level.size
            level = _pyr_down_wrapped(level)
    return TextureBank(np.concatenate(chunks), fam_off, np.array(lvl_off, np.int32))


# ---------------------------------------------------------------------------------------------
# meshes (numpy; every part is convex, triangles are re-oriented outward afterwards)

def _box_mesh(center_xy, z0: float, size, yaw_rad: float) -> tuple[np.ndarray, np.ndarray]:
    l, w, h = size
    sx, sy, sz = np.meshgrid([-l / 2, l / 2], [-w / 2, w / 2], [0.0, h], indexing="ij")
    v = np.stack([sx.ravel(), sy.ravel(), sz.ravel()], axis=1)   # index = 4*ix + 2*iy + iz
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    v = v @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) + [center_xy[0], center_xy[1], z0]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [t for a, b, c_, d in quads for t in ((a, b, c_), (a, c_, d))]
    return v, np.array(tris)


def _frustum_mesh(center_xy, z0: float, r0: float, r1: float, height: float,
                  segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Cylinder (r1 == r0) or cone (r1 == 0) with caps, `segments` flat sides."""
    ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    bottom = np.c_[ring * r0 + center_xy, np.full(segments, z0)]
    top = np.c_[ring * max(r1, 1e-4) + center_xy, np.full(segments, z0 + height)]
    v = np.vstack([bottom, top, [[center_xy[0], center_xy[1], z0]], [[center_xy[0], center_xy[1], z0 + height]]])
    cb, ct = 2 * segments, 2 * segments + 1
    tris = []
    for i in range(segments):
        j = (i + 1) % segments
        tris.append((cb, j, i))
        if r1 > 0:
            tris += [(i, j, segments + j), (i, segments + j, segments + i), (ct, segments + i, segments + j)]
        else:   # cone: sides meet at the apex (top centre)
            tris.append((i, j, ct))
    return v, np.array(tris)


def _orient_outward(v: np.ndarray, tris: np.ndarray) -> np.ndarray:
    centroid = v.mean(axis=0)
    a, b, c = v[tris[:, 0]], v[tris[:, 1]], v[tris[:, 2]]
    n = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", n, (a + b + c) / 3 - centroid) < 0
    tris = tris.copy()
    tris[flip] = tris[flip][:, [0, 2, 1]]
    return tris


# ---------------------------------------------------------------------------------------------

@dataclass
class _Part:
    vertices: np.ndarray
    triangles: np.ndarray
    entity: int
    material: str


class Scene:
    """Static raycasting world of one scenario.

    Plane table (index p, the sentinel p == num_planes means "sky / no hit"):
      plane_normal[p] (ENU unit), plane_d[p] (n . x = d), plane_entity[p], plane_ground[p],
      plane_rgb[p] (uint8, lit base colour), plane_gray[p], plane_tex[p] (texel offset of the
      texture family), plane_inv_texel[p] (1/m), plane_e1/e2[p] (texture axes, ENU unit),
      plane_tex_offset_m[p] (2,).
    """

    def __init__(self, scenario: Scenario):
        self.scenario = scenario
        self.entities: list[Entity] = [Entity(KIND_GROUND, -1, "", "ground")]
        self.target_boxes: list[TargetBox] = []
        parts = self._ground_parts() + self._object_parts() + self._target_parts()
        self._build_tables(parts)
        self._build_raycaster(parts)

    # ---- parts ----

    def _sink(self, radius_m: float) -> float:
        """How far to bury a footprint of this radius so no edge floats on a slope."""
        return radius_m * math.tan(math.radians(self.scenario.ground.slope_deg))

    def _ground_parts(self) -> list[_Part]:
        hx, hy = (s / 2 for s in self.scenario.ground.size_m)
        xy = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        z = [self.scenario.ground_height_m(x, y) for x, y in xy]
        v = np.c_[xy, z]
        return [_Part(v, np.array([[0, 1, 2], [0, 2, 3]]), 0, self.scenario.ground.material)]

    def _object_parts(self) -> list[_Part]:
        parts = []
        for i, obj in enumerate(self.scenario.objects):
            ent = len(self.entities)
            self.entities.append(Entity(KIND_OBJECT, i, "", obj.name or f"{obj.type}{i}"))
            x, y = obj.position_m
            g = self.scenario.ground_height_m(x, y)
            if isinstance(obj, BoxObject):
                sink = 0.0 if obj.elevation_m > 0 else self._sink(math.hypot(*obj.size_m[:2]) / 2)
                size = (obj.size_m[0], obj.size_m[1], obj.size_m[2] + sink)
                v, t = _box_mesh((x, y), g + obj.elevation_m - sink, size, math.radians(obj.yaw_deg))
                parts.append(_Part(v, t, ent, obj.material_name()))
            elif isinstance(obj, PoleObject):
                sink = self._sink(obj.radius_m)
                v, t = _frustum_mesh((x, y), g - sink, obj.radius_m, obj.radius_m, obj.height_m + sink, 12)
                parts.append(_Part(v, t, ent, obj.material))
            elif isinstance(obj, TreeObject):
                sink = self._sink(obj.trunk_radius_m)
                v, t = _frustum_mesh((x, y), g - sink, obj.trunk_radius_m, obj.trunk_radius_m,
                                     obj.height_m * 0.9 + sink, 10)
                parts.append(_Part(v, t, ent, "bark"))
                v, t = _frustum_mesh((x, y), g + obj.crown_base_m, obj.crown_radius_m, 0.0,
                                     obj.height_m - obj.crown_base_m, 10)
                parts.append(_Part(v, t, ent, "foliage"))
        return parts

    def _target_parts(self) -> list[_Part]:
        parts = []
        for i, tgt in enumerate(self.scenario.targets):
            ent = len(self.entities)
            self.entities.append(Entity(KIND_TARGET, i, tgt.class_name, tgt.name or f"{tgt.class_name}{i}"))
            x, y = tgt.position_m
            g = self.scenario.ground_height_m(x, y)
            l, w, h = tgt.size
            yaw = math.radians(tgt.yaw_deg)
            self.target_boxes.append(TargetBox(ent, i, tgt.class_name, np.array([x, y, g + h / 2]), (l, w, h), yaw))
            sink = self._sink(math.hypot(l, w) / 2)
            for (cx, cw, z0, z1, cl) in _target_shape(tgt):
                c, s = math.cos(yaw), math.sin(yaw)
                centre = (x + c * cx * l, y + s * cx * l)
                zb = g + z0 * h - (sink if z0 == 0 else 0.0)
                v, t = _box_mesh(centre, zb, (cl * l, cw * w, (z1 - z0) * h + (sink if z0 == 0 else 0.0)), yaw)
                parts.append(_Part(v, t, ent, tgt.material_name()))
        return parts

    # ---- tables ----

    def _build_tables(self, parts: list[_Part]) -> None:
        bank = texture_bank()
        rng = np.random.default_rng(self.scenario.seed)
        ent_offsets = rng.uniform(0, 1000.0, size=(len(self.entities), 2))
        la = self.scenario.lighting
        az, el = math.radians(la.sun_azimuth_deg), math.radians(la.sun_elevation_deg)
        sun = np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])

        normals, ds, ents, mats, tri_plane = [], [], [], [], []
        for part in parts:
            tris = part.triangles if part.entity == 0 else _orient_outward(part.vertices, part.triangles)
            part.triangles = tris
            a, b, c = (part.vertices[tris[:, k]] for k in range(3))
            n = np.cross(b - a, c - a)
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            d = np.einsum("ij,ij->i", n, a)
            key = np.c_[np.round(n * 1e4), np.round(d * 1e3)].astype(np.int64)
            uniq, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
            tri_plane.append(inv.ravel() + len(normals))
            for k in first:
                normals.append(n[k])
                ds.append(d[k])
                ents.append(part.entity)
                mats.append(part.material)
        self.num_planes = npl = len(normals)
        self.tri_plane = np.append(np.concatenate(tri_plane), npl).astype(np.int32)  # + miss sentinel

        # Per-plane tables with one extra sentinel row for "sky".
        self.plane_normal = np.vstack([np.array(normals), np.zeros((1, 3))])
        self.plane_d = np.append(np.array(ds), 0.0)
        self.plane_entity = np.append(np.array(ents, np.int32), -1).astype(np.int32)
        self.plane_ground = self.plane_entity == 0
        rgb = np.zeros((npl + 1, 3))
        fam_off = np.zeros(npl + 1, np.int64)
        inv_texel = np.zeros(npl + 1)
        for p, m in enumerate(mats):
            base, fam, texel = MATERIALS[m]
            shade = la.ambient + (1.0 - la.ambient) * max(0.0, float(self.plane_normal[p] @ sun))
            rgb[p] = np.asarray(base) * shade
            fam_off[p] = bank.family_offset[fam]
            inv_texel[p] = 1.0 / texel
        rgb[npl] = la.sky_rgb
        fam_off[npl] = bank.family_offset["flat"]
        self.plane_rgb = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
        self.plane_rgb_cols = [np.ascontiguousarray(self.plane_rgb[:, c]) for c in range(3)]
        self.plane_gray = np.clip(np.rint(rgb @ [0.299, 0.587, 0.114]), 0, 255).astype(np.uint8)
        self.plane_tex = fam_off.astype(np.int32)
        self.plane_inv_texel = inv_texel

        # Texture axes: vertical faces keep "up" as the texture's v axis so facade rectangles
        # stand upright; near-horizontal faces use East / North.
        nrm = self.plane_normal[:npl]
        up = np.array([0.0, 0.0, 1.0])
        east = np.array([1.0, 0.0, 0.0])
        vertical = np.abs(nrm[:, 2]) < 0.95
        e2 = np.where(vertical[:, None], up - nrm[:, 2:3] * nrm, 0.0)
        e1 = np.where(vertical[:, None], 0.0, east - nrm[:, 0:1] * nrm)
        e2[vertical] /= np.linalg.norm(e2[vertical], axis=1, keepdims=True)
        e1[vertical] = np.cross(e2[vertical], nrm[vertical])
        e1[~vertical] /= np.linalg.norm(e1[~vertical], axis=1, keepdims=True)
        e2[~vertical] = np.cross(nrm[~vertical], e1[~vertical])
        self.plane_e1 = np.vstack([e1, np.zeros((1, 3))])
        self.plane_e2 = np.vstack([e2, np.zeros((1, 3))])
        self.plane_tex_offset_m = np.vstack([ent_offsets[self.plane_entity[:npl]], np.zeros((1, 2))])
        self.texels = bank.texels
        self.tex_level_offset = bank.level_offset

    def _build_raycaster(self, parts: list[_Part]) -> None:
        verts, tris, base = [], [], 0
        for part in parts:
            verts.append(part.vertices)
            tris.append(part.triangles + base)
            base += len(part.vertices)
        self.vertices = np.vstack(verts).astype(np.float32)
        self.triangles = np.vstack(tris).astype(np.uint32)
        self.raycaster = o3d.t.geometry.RaycastingScene()
        self.raycaster.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))

    # ---- queries ----

    @staticmethod
    def make_rays(origin_m, rot: np.ndarray, x: np.ndarray, y: np.ndarray,
                  z: np.ndarray | None = None) -> np.ndarray:
        """(N, 6) float32 rays from one origin along rot @ (x, y, z) (z = 1 when None).

        Direction columns are passed as separate 1-D arrays and written column by column:
        numpy ops on (N, 3) arrays run an inner loop of length 3 and are ~10x slower."""
        rays = np.empty((len(x), 6), np.float32)
        for k in range(3):
            rays[:, k] = origin_m[k]
            col = rays[:, 3 + k]
            np.multiply(x, np.float32(rot[k, 0]), out=col)
            col += np.float32(rot[k, 1]) * y
            col += np.float32(rot[k, 2]) if z is None else np.float32(rot[k, 2]) * z
        return rays

    def cast_rays(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cast (N, 6) float32 rays (origin, direction; ENU).

        Returns (t, plane): t float32 in units of each direction's length (MISS_DEPTH_M where
        nothing is hit) and plane int32 (num_planes where nothing is hit).
        """
        out = self.raycaster.cast_rays(o3d.core.Tensor.from_numpy(rays))
        t = np.minimum(out["t_hit"].numpy(), np.float32(MISS_DEPTH_M))
        # A miss has primitive id 0xFFFFFFFF: clipping maps it onto the sentinel entry.
        plane = np.take(self.tri_plane, out["primitive_ids"].numpy(), mode="clip")
        return t, plane

    def obstacle_distance_m(self, points_m: np.ndarray) -> np.ndarray:
        """Distance (m) from each ENU point to the nearest non-ground surface: how close a
        vehicle there is to hitting something (evaluation and tests; built on first use)."""
        if not hasattr(self, "_obstacles_rc"):
            keep = ~np.take(self.plane_ground, self.tri_plane[: len(self.triangles)])
            self._obstacles_rc = o3d.t.geometry.RaycastingScene()
            self._obstacles_rc.add_triangles(o3d.core.Tensor(self.vertices),
                                             o3d.core.Tensor(np.ascontiguousarray(self.triangles[keep])))
        q = o3d.core.Tensor(np.asarray(points_m, dtype=np.float32).reshape(-1, 3))
        return self._obstacles_rc.compute_distance(q).numpy()

    def cast(self, origin_m, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Convenience: rays from one origin (3,) or origins (N, 3) along dirs (N, 3) ENU."""
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = origin_m
        rays[:, 3:] = dirs
        return self.cast_rays(rays)


def _target_shape(tgt: Target) -> list[tuple[float, float, float, float, float]]:
    """Boxes making up a target, as fractions of its (l, w, h):
    (centre offset along l, width, z bottom, z top, length). A recognisable silhouette is enough;
    the truth box is always the full (l, w, h) box."""
    shapes = {
        "person": [(0.0, 1.0, 0.0, 0.86, 1.0), (0.0, 0.45, 0.86, 1.0, 0.5)],
        "car": [(0.0, 0.9, 0.0, 0.1, 0.8), (0.0, 1.0, 0.1, 0.55, 1.0), (-0.1, 0.9, 0.55, 1.0, 0.55)],
        "truck": [(0.0, 0.9, 0.0, 0.1, 0.9), (-0.12, 1.0, 0.1, 1.0, 0.76), (0.38, 1.0, 0.1, 0.75, 0.22)],
        "bus": [(0.0, 0.9, 0.0, 0.1, 0.9), (0.0, 1.0, 0.1, 1.0, 1.0)],
    }
    return shapes.get(tgt.class_name, [(0.0, 1.0, 0.0, 1.0, 1.0)])


@functools.lru_cache(maxsize=4)
def get_scene(scenario: Scenario) -> Scene:
    """Build (once) the scene of a scenario; sensors of one simulator share it."""
    return Scene(scenario)
