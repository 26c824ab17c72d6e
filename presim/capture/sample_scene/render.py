"""Ray casting the sample room: Open3D ``RaycastingScene`` for the hits, numba kernels for shading.

color = procedural albedo(material, hit point) x Lambertian shading of fixed point lights with hard
shadows -- nothing depends on the viewing direction, so reprojection with exact depth is near-exact.
:func:`scene_raycaster` caches one :class:`SceneRaycaster` per (seed, config) per process.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numba
import numpy as np

from presim.capture.procedural import SRGB_LUT, SRGB_STEPS, NoiseField, albedo
from presim.capture.sample_scene.config import SampleSceneConfig
from presim.capture.sample_scene.layout import SampleLayout, sample_layout
from presim.geometry import Intrinsics, check_rigid, invert

__all__ = ["RenderedView", "SceneRaycaster", "scene_raycaster", "render_view", "pixel_rays"]


@dataclass(frozen=True)
class RenderedView:
    """A ray-cast view. Arrays are (H, W)."""

    color: np.ndarray
    """uint8 (H, W, 3) sRGB."""
    depth_m: np.ndarray
    """float32 exact z-depth, 0 = no surface."""
    object_id: np.ndarray
    """int32 obj_id, 0 = background."""
    albedo_lum: np.ndarray
    """float32 linear albedo luminance of the hit surface (0 where no surface)."""
    cos_incidence: np.ndarray
    """float32 |cos| of the angle between ray and surface normal (0 where no surface)."""


class SceneRaycaster:
    """World-frame triangle soup + per-triangle part index, an Open3D RaycastingScene and shading."""

    def __init__(self, layout: SampleLayout, seed: int, shadows: bool):
        import open3d as o3d

        self.layout = layout
        self.shadows = shadows
        self.noise = NoiseField(seed)
        verts, tris, norms, tri_part, ranges = [], [], [], [], []
        off = ntri = 0
        for k, p in enumerate(layout.parts):
            m = p.mesh.transformed(p.T_world_part)
            verts.append(m.vertices)
            norms.append(m.normals)
            tris.append(m.triangles + off)
            tri_part.append(np.full(len(m.triangles), k, np.int32))
            ranges.append((ntri, ntri + len(m.triangles)))
            off += len(m.vertices)
            ntri += len(m.triangles)
        self.vertices = np.concatenate(verts).astype(np.float32)
        self.triangles = np.concatenate(tris).astype(np.uint32)
        self.vertex_normals = np.concatenate(norms).astype(np.float32)
        self.tri_part = np.concatenate(tri_part)
        self.part_ranges = ranges
        self.part_obj_id = np.array([p.obj_id for p in layout.parts], np.int32)
        self.T_part_world = np.stack([invert(p.T_world_part) for p in layout.parts])
        self.light_array = np.array([[*l["pos"], l["intensity"], float(l["shadow"])] for l in layout.lights])
        shadowed = [k for k, l in enumerate(layout.lights) if l["shadow"]]
        if len(shadowed) > 1:
            raise ValueError("only one light may cast shadows")
        self.shadow_light = shadowed[0] if shadowed else -1
        self._object_rcs = None  # per-object scenes, built on first use
        self.rc = o3d.t.geometry.RaycastingScene()
        self.rc.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))
        self._o3d = o3d

    def render(self, T_world_cam: np.ndarray, K: Intrinsics) -> RenderedView:
        o3c = self._o3d.core
        h, w = K.height, K.width
        d_cam = pixel_rays(K)
        R = np.ascontiguousarray(T_world_cam[:3, :3], dtype=np.float64)
        c = np.ascontiguousarray(T_world_cam[:3, 3], dtype=np.float64)
        ans = self.rc.cast_rays(o3c.Tensor(_make_rays(d_cam, R, c)))
        t_hit = ans["t_hit"].numpy()
        prim_all = ans["primitive_ids"].numpy()
        hit_idx = np.nonzero(np.isfinite(t_hit))[0]
        # Visit hits grouped by part: contiguous slices instead of one boolean mask per part.
        part = self.tri_part[prim_all[hit_idx]]
        order = np.argsort(part, kind="stable")
        hit_idx, part = hit_idx[order], part[order]

        p_world, n, p_loc, n_loc, E, main = _surface_kernel(
            hit_idx, d_cam, R, c, t_hit, prim_all, ans["primitive_uvs"].numpy(), self.triangles,
            self.vertex_normals, part, self.T_part_world, self.light_array, float(self.layout.ambient))
        alb = np.empty((len(hit_idx), 3))
        bounds = np.searchsorted(part, np.arange(len(self.layout.parts) + 1))
        for k in range(len(self.layout.parts)):
            lo, hi = bounds[k], bounds[k + 1]
            if hi > lo:
                alb[lo:hi] = albedo(self.layout.parts[k].material, p_loc[lo:hi], n_loc[lo:hi], self.noise)

        if self.shadows and self.shadow_light >= 0:
            lit = np.nonzero(main > 0)[0]
            L = np.asarray(self.layout.lights[self.shadow_light]["pos"], dtype=np.float64)
            # Offset along the normal so a surface does not shadow itself.
            o = p_world[lit] + n[lit] * 2e-3
            rays = np.empty((len(lit), 6), np.float32)
            rays[:, :3] = o
            rays[:, 3:] = L - o
            occ = self.rc.test_occlusions(o3c.Tensor(rays), tnear=0.0, tfar=1.0).numpy()
            E[lit[occ]] -= main[lit[occ]]
        color, depth, obj, lum, cos_inc = _compose_kernel(
            h * w, hit_idx, alb, E, t_hit, d_cam, R, n, part, self.part_obj_id, SRGB_LUT, SRGB_STEPS)
        return RenderedView(color.reshape(h, w, 3), depth.reshape(h, w), obj.reshape(h, w),
                            lum.reshape(h, w), cos_inc.reshape(h, w))


    def object_silhouettes(self, T_world_cam: np.ndarray, K: Intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each object ray cast alone: ``(obj_ids (K,), masks bool (K, H, W), depth_m float32 (K, H, W))``."""
        o3c = self._o3d.core
        if self._object_rcs is None:
            self._object_rcs = []
            for k, p in enumerate(self.layout.parts):
                if p.obj_id:
                    a, b = self.part_ranges[k]
                    tris = self.triangles[a:b]
                    used, inv = np.unique(tris.reshape(-1), return_inverse=True)
                    rc = self._o3d.t.geometry.RaycastingScene()
                    rc.add_triangles(o3c.Tensor(self.vertices[used]),
                                     o3c.Tensor(inv.reshape(-1, 3).astype(np.uint32)))
                    self._object_rcs.append((p.obj_id, rc))
        R = np.ascontiguousarray(T_world_cam[:3, :3], dtype=np.float64)
        c = np.ascontiguousarray(T_world_cam[:3, 3], dtype=np.float64)
        rays = o3c.Tensor(_make_rays(pixel_rays(K), R, c))
        ids, masks, depths = [], [], []
        for obj_id, rc in self._object_rcs:
            t = rc.cast_rays(rays)["t_hit"].numpy().reshape(K.height, K.width)
            hit = np.isfinite(t)
            ids.append(obj_id)
            masks.append(hit)
            depths.append(np.where(hit, t, 0.0).astype(np.float32))
        return np.array(ids, np.int32), np.stack(masks), np.stack(depths)


@numba.njit(parallel=True, cache=True)
def _make_rays(d_cam, R, c):
    """(M, 6) float32 rays [origin, R @ d_cam] for Open3D."""
    m = d_cam.shape[0]
    rays = np.empty((m, 6), np.float32)
    for i in numba.prange(m):
        for a in range(3):
            rays[i, a] = c[a]
            rays[i, 3 + a] = R[a, 0] * d_cam[i, 0] + R[a, 1] * d_cam[i, 1] + R[a, 2] * d_cam[i, 2]
    return rays


@numba.njit(parallel=True, cache=True)
def _compose_kernel(num_pixels, hit_idx, alb, E, t_hit, d_cam, R, n, part, part_obj_id, lut, steps):
    """Scatter the shaded hits into full images: sRGB color, exact depth, object id, albedo
    luminance and |cos| of incidence (0 / black where a ray hits nothing)."""
    color = np.zeros((num_pixels, 3), np.uint8)
    depth = np.zeros(num_pixels, np.float32)
    obj = np.zeros(num_pixels, np.int32)
    lum = np.zeros(num_pixels, np.float32)
    cos_inc = np.zeros(num_pixels, np.float32)
    for j in numba.prange(hit_idx.shape[0]):
        i = hit_idx[j]
        for a in range(3):
            x = min(max(alb[j, a] * E[j], 0.0), 1.0)
            color[i, a] = lut[np.int64(np.rint(x * steps))]
        depth[i] = t_hit[i]  # rays have camera-frame z = 1: t_hit is the z-depth
        obj[i] = part_obj_id[part[j]]
        lum[i] = 0.2126 * alb[j, 0] + 0.7152 * alb[j, 1] + 0.0722 * alb[j, 2]
        dx = R[0, 0] * d_cam[i, 0] + R[0, 1] * d_cam[i, 1] + R[0, 2] * d_cam[i, 2]
        dy = R[1, 0] * d_cam[i, 0] + R[1, 1] * d_cam[i, 1] + R[1, 2] * d_cam[i, 2]
        dz = R[2, 0] * d_cam[i, 0] + R[2, 1] * d_cam[i, 1] + R[2, 2] * d_cam[i, 2]
        cos_inc[i] = abs(dx * n[j, 0] + dy * n[j, 1] + dz * n[j, 2]) / np.sqrt(dx * dx + dy * dy + dz * dz)
    return color, depth, obj, lum, cos_inc


@numba.njit(parallel=True, cache=True)
def _surface_kernel(hit_idx, d_cam, R, c, t_hit, prim, bary, triangles, vertex_normals, part, T_part_world,
                    lights, ambient):
    """Per hit pixel ``hit_idx[j]``: world point, interpolated unit normal, both in the part's frame,
    Lambertian irradiance of all lights + ambient (unshadowed) and the shadow-casting light's share.
    ``lights`` rows are (x, y, z, intensity, casts_shadow)."""
    m = hit_idx.shape[0]
    p_world = np.empty((m, 3))
    n_out = np.empty((m, 3))
    p_loc = np.empty((m, 3))
    n_loc = np.empty((m, 3))
    E = np.empty(m)
    main = np.zeros(m)
    for j in numba.prange(m):
        i = hit_idx[j]
        t = np.float64(t_hit[i])
        px = c[0] + (R[0, 0] * d_cam[i, 0] + R[0, 1] * d_cam[i, 1] + R[0, 2] * d_cam[i, 2]) * t
        py = c[1] + (R[1, 0] * d_cam[i, 0] + R[1, 1] * d_cam[i, 1] + R[1, 2] * d_cam[i, 2]) * t
        pz = c[2] + (R[2, 0] * d_cam[i, 0] + R[2, 1] * d_cam[i, 1] + R[2, 2] * d_cam[i, 2]) * t
        b1 = np.float64(bary[i, 0])
        b2 = np.float64(bary[i, 1])
        b0 = 1.0 - b1 - b2
        tri = prim[i]
        v0, v1, v2 = triangles[tri, 0], triangles[tri, 1], triangles[tri, 2]
        nx = b0 * vertex_normals[v0, 0] + b1 * vertex_normals[v1, 0] + b2 * vertex_normals[v2, 0]
        ny = b0 * vertex_normals[v0, 1] + b1 * vertex_normals[v1, 1] + b2 * vertex_normals[v2, 1]
        nz = b0 * vertex_normals[v0, 2] + b1 * vertex_normals[v1, 2] + b2 * vertex_normals[v2, 2]
        nn = np.sqrt(nx * nx + ny * ny + nz * nz)
        nx, ny, nz = nx / nn, ny / nn, nz / nn
        p_world[j, 0], p_world[j, 1], p_world[j, 2] = px, py, pz
        n_out[j, 0], n_out[j, 1], n_out[j, 2] = nx, ny, nz
        T = T_part_world[part[j]]
        for a in range(3):
            p_loc[j, a] = T[a, 0] * px + T[a, 1] * py + T[a, 2] * pz + T[a, 3]
            n_loc[j, a] = T[a, 0] * nx + T[a, 1] * ny + T[a, 2] * nz
        e = ambient
        for k in range(lights.shape[0]):
            lx, ly, lz = lights[k, 0] - px, lights[k, 1] - py, lights[k, 2] - pz
            dist = np.sqrt(lx * lx + ly * ly + lz * lz)
            cs = (nx * lx + ny * ly + nz * lz) / dist
            if cs > 0.0:
                contrib = lights[k, 3] * cs / (1.0 + (dist / 2.0) ** 2)
                e += contrib
                if lights[k, 4] > 0.0:
                    main[j] = contrib
        E[j] = e
    return p_world, n_out, p_loc, n_loc, E, main


@functools.lru_cache(maxsize=8)
def pixel_rays(K: Intrinsics) -> np.ndarray:
    """(H*W, 3) float64 camera-frame ray directions with z = 1 through the pixel centres (read-only)."""
    u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
    d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], -1).reshape(-1, 3)
    d.setflags(write=False)
    return d


@functools.lru_cache(maxsize=4)
def scene_raycaster(seed: int, config: SampleSceneConfig) -> SceneRaycaster:
    return SceneRaycaster(sample_layout(seed, config), seed, config.shadows)


def render_view(seed: int, config: SampleSceneConfig, T_world_cam: np.ndarray, K: Intrinsics) -> RenderedView:
    """Ray cast the sample room of ``seed`` at ``T_world_cam`` (4x4, OpenCV camera-to-world)."""
    if not isinstance(K, Intrinsics):
        raise TypeError(f"K must be presim.geometry.Intrinsics, got {type(K).__name__}")
    T = np.asarray(T_world_cam, dtype=np.float64)
    # Validate only: the pose is used as given, so a capture pose re-renders bit for bit.
    check_rigid(T, "T_world_cam")
    return scene_raycaster(int(seed), config).render(T, K)
