"""The built-in sample scene: a procedural, textured room captured along a hand-held trajectory.

:func:`build_sample_scene` builds, deterministically from a seed, a ~5 x 4 m room (floor, four walls
with a door to a short corridor, ceiling, a rug, a table, a bookshelf, a sideboard, a poster, a dark TV,
cardboard boxes and a bin on the floor) and 3-5 textured objects standing on the table (box, can,
non-convex bracket, ball, irregular rock; 5-25 cm). It ray casts every pixel of every frame with
Open3D's ``RaycastingScene``: color = procedural albedo(material, hit point) x Lambertian shading
of fixed point lights with hard shadows -- nothing depends on the viewing direction, so a pixel's color
is a property of the surface point alone and reprojection with exact depth and poses is near-exact.

The saved scene's ``depth.npy`` is a *realistically corrupted* copy of the exact depth
(:func:`corrupt_depth`: noise growing with z^2, holes on dark / grazing / out-of-range surfaces and
behind depth edges, a few pixels of color/depth misregistration); the exact depth and the rest of the
ground truth are in ``DST/ground_truth/`` (see docs/sample-scene.md)::

    ground_truth/
      depth_clean.npy   float32 (N, H, W) exact z-depth, metres (0 = no surface)
      object_id.npy     uint8   (N, H, W) obj_id of the visible object, 0 = background
      room.ply          the whole scene (room + furniture + objects) in world metres, per-vertex colors
      parts.json        every part: name, kind, obj_id, world AABB, triangle range in room.ply
      sample.json       seed + SampleSceneConfig + lights: enough to re-render any view exactly

Example:
    >>> from presim.capture.sample_scene import build_sample_scene, render_ground_truth
    >>> dst = build_sample_scene("out/sample", seed=0)                     # doctest: +SKIP
    >>> from presim.capture.store import load_scene
    >>> scene = load_scene(dst)                                            # doctest: +SKIP
    >>> color, depth_m, obj = render_ground_truth(dst, scene.T_world_cam[0], scene.intrinsics[0])  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import shutil
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from presim.capture.procedural import (
    _SRGB_LUT, _SRGB_STEPS, Material, Mesh, NoiseField, albedo, box_mesh, cylinder_mesh, ellipsoid_mesh,
    merge_meshes, rock_mesh, srgb_encode, write_ply,
)
from presim.capture.scene import (
    ArrayFrameSource, FloorPlane, Scene, SceneError, SceneMeta, SceneObject,
)
from presim.geometry import Intrinsics, check_rigid, compose, invert, look_at, make_pose, rotation_z
from presim.io_utils import atomic_dir, atomic_write_json, progress

__all__ = [
    "SampleSceneConfig", "SamplePart", "SampleGroundTruth", "RenderedView",
    "build_sample_scene", "load_sample_ground_truth", "clean_scene", "render_ground_truth",
    "render_object_silhouettes",
    "render_view", "corrupt_depth", "capture_trajectory", "sample_layout",
]

SAMPLE_VERSION = 1
GT_DIR = "ground_truth"


@dataclass(frozen=True)
class SampleSceneConfig:
    """How the sample scene is built, captured and corrupted. All fields have working defaults."""

    width: int = 640
    """Image width, pixels."""
    height: int = 480
    """Image height, pixels."""
    num_frames: int = 60
    """Frames along the capture trajectory (its shape does not change; more frames = denser)."""
    hfov_deg: float = 62.0
    """Horizontal field of view (Kinect-like); square pixels, principal point at the image centre."""
    frame_rate_hz: float = 5.0
    """Time stamps are ``frame_idx / frame_rate_hz`` seconds."""
    num_objects: int = 5
    """Objects on the table, 3..5, taken in this order: box, can, bracket (non-convex), ball, rock."""
    door: bool = True
    """A door-sized gap in the north wall leading into a short closed corridor."""
    ceiling: bool = True
    """Close the room with a ceiling (otherwise upward rays see nothing: depth 0, black)."""
    shadows: bool = True
    """Hard shadows of the main light (one shadow ray per lit pixel)."""
    # ---- depth corruption (see corrupt_depth) ----
    noise_sigma0_m: float = 0.0005
    """Depth noise standard deviation at z = 0, metres."""
    noise_k_per_m: float = 0.0015
    """Depth noise grows as ``sigma(z) = noise_sigma0_m + noise_k_per_m * z**2`` (structured-light)."""
    min_range_m: float = 0.3
    """No depth closer than this (sensor minimum range)."""
    max_range_m: float = 4.0
    """No depth beyond this (sensor maximum range)."""
    dark_albedo: float = 0.05
    """Surfaces with albedo luminance below this return no depth (with ``dark_dropout`` probability)."""
    dark_dropout: float = 0.9
    """Probability that a dark pixel has no depth."""
    grazing_deg: float = 78.0
    """Incidence angle (ray vs. surface normal) around which depth drops out (ramp +-6 degrees)."""
    edge_shadow_px: int = 3
    """Width of the hole on the background left of a nearer surface (projector shadow), pixels."""
    edge_dilate_px: int = 1
    """Foreground depth grows this many pixels over the background at depth edges."""
    shift_px: tuple[int, int] = (2, 1)
    """Color/depth misregistration: depth is shifted by (du, dv) pixels relative to the color."""
    speckle_dropout: float = 0.003
    """Fraction of random isolated missing pixels."""


@dataclass(frozen=True)
class SamplePart:
    """One part of the sample room (a wall, the table, an obstacle, an object, ...)."""

    name: str
    kind: str
    """floor | wall | ceiling | decor | furniture | obstacle | object."""
    obj_id: int
    """1..K for table objects, 0 otherwise."""
    aabb_min: tuple[float, float, float]
    """World-frame axis-aligned bounding box, metres."""
    aabb_max: tuple[float, float, float]
    tri_start: int
    """Triangles ``[tri_start, tri_end)`` of ``room.ply`` belong to this part."""
    tri_end: int


@dataclass(frozen=True)
class SampleGroundTruth:
    """Ground truth of a built sample scene (arrays memory-mapped)."""

    path: Path
    seed: int
    config: SampleSceneConfig
    depth_clean_m: np.ndarray
    """float32 (N, H, W) exact z-depth, metres, 0 where no surface."""
    object_id: np.ndarray
    """uint8 (N, H, W) obj_id per pixel, 0 = not an object."""
    room_mesh_path: Path
    """PLY of the whole scene (world frame, metres, per-vertex colors)."""
    parts: tuple[SamplePart, ...]
    table_top_z_m: float
    """Height of the table top (objects stand on it)."""


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


# ---- layout -------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Part:
    name: str
    kind: str
    mesh: Mesh                  # in the part frame
    T_world_part: np.ndarray
    material: Material
    obj_id: int = 0


@dataclass
class _Layout:
    parts: list[_Part]
    table_top_z_m: float
    table_centre_xy: np.ndarray
    objects_centre: np.ndarray
    lights: list[dict] = field(default_factory=list)
    ambient: float = 0.3


def _hsv(h: float, s: float, v: float) -> tuple[float, float, float]:
    i = int(h * 6) % 6
    f = h * 6 - np.floor(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]


def sample_layout(seed: int, config: SampleSceneConfig = SampleSceneConfig()) -> _Layout:
    """The room for ``seed``: parts with meshes, world poses and materials (pure, deterministic)."""
    rng = np.random.default_rng([seed, 1])
    I = np.eye(4)
    parts: list[_Part] = []

    def add(name, kind, mesh, mat, T=I, obj_id=0):
        parts.append(_Part(name, kind, mesh, np.asarray(T, dtype=np.float64), mat, obj_id))

    X, Y, H, t = 2.5, 2.0, 2.6, 0.1  # interior half-sizes, height, wall thickness
    door_x = (1.2, 2.1)
    corr_y = 3.4
    ext_y = corr_y + t if config.door else Y + t
    wall_hue = rng.uniform(0, 1)
    plaster = Material("plaster", _hsv(wall_hue, 0.12, 0.75), _hsv(wall_hue + 0.05, 0.2, 0.6), 0.4, 1.0)
    plaster2 = Material("wallpaper", _hsv(wall_hue + 0.5, 0.2, 0.75), _hsv(wall_hue + 0.45, 0.45, 0.5), 0.16, 2.0)
    brick = Material("brick", _hsv(0.03 + 0.03 * rng.uniform(), 0.65, 0.55), (0.7, 0.68, 0.62), 0.22, 3.0)
    floor_mat = Material("planks", _hsv(0.08, 0.55, 0.55), _hsv(0.07, 0.6, 0.3), 0.14, 4.0)
    add("floor", "floor", box_mesh([-X - t, -Y - t, -0.05], [X + t, ext_y, 0.0]), floor_mat)
    if config.ceiling:
        add("ceiling", "ceiling", box_mesh([-X - t, -Y - t, H], [X + t, ext_y, H + 0.05]),
            Material("plaster", (0.8, 0.8, 0.78), (0.7, 0.7, 0.68), 0.5, 5.0))
    add("wall_south", "wall", box_mesh([-X - t, -Y - t, 0], [X + t, -Y, H]), brick)
    add("wall_west", "wall", box_mesh([-X - t, -Y - t, 0], [-X, Y + t, H]), plaster)
    add("wall_east", "wall", box_mesh([X, -Y - t, 0], [X + t, Y + t, H]), plaster)
    if config.door:
        add("wall_north_a", "wall", box_mesh([-X - t, Y, 0], [door_x[0], Y + t, H]), plaster2)
        add("wall_north_b", "wall", box_mesh([door_x[1], Y, 0], [X + t, Y + t, H]), plaster2)
        add("wall_north_lintel", "wall", box_mesh([door_x[0], Y, 2.05], [door_x[1], Y + t, H]), plaster2)
        cx0, cx1 = door_x[0] - 0.05, door_x[1] + 0.05
        add("corridor_west", "wall", box_mesh([cx0 - t, Y + t, 0], [cx0, ext_y, H]), plaster)
        add("corridor_east", "wall", box_mesh([cx1, Y + t, 0], [cx1 + t, ext_y, H]), plaster)
        add("corridor_end", "wall", box_mesh([cx0 - t, corr_y, 0], [cx1 + t, ext_y, H]), brick)
    else:
        add("wall_north", "wall", box_mesh([-X - t, Y, 0], [X + t, Y + t, H]), plaster2)

    # Decor on the walls.
    add("poster", "decor", box_mesh([X - 0.012, -0.7, 1.0], [X, 0.4, 1.75]),
        Material("poster", (0.9, 0.85, 0.8), scale_m=0.35, salt=6.0 + rng.uniform(0, 50)))
    add("tv", "decor", box_mesh([-X, -0.55, 0.95], [-X + 0.05, 0.55, 1.6]),
        Material("dark", (0.025, 0.025, 0.03), scale_m=0.3, salt=7.0))

    # Table (jittered), rug under it.
    tc = np.array([0.3, -0.25]) + rng.uniform(-0.15, 0.15, 2)
    top_z = 0.75
    tl, tw, th = 1.2, 0.8, 0.04
    wood = Material("wood", _hsv(0.07, 0.55, 0.6), _hsv(0.06, 0.65, 0.35), 0.08, 8.0)
    add("rug", "decor", box_mesh([tc[0] - 1.0, tc[1] - 0.7, 0.0], [tc[0] + 1.0, tc[1] + 0.7, 0.008]),
        Material("checker", _hsv(rng.uniform(), 0.5, 0.5), (0.75, 0.72, 0.65), 0.12, 9.0))
    add("table_top", "furniture", box_mesh([tc[0] - tl / 2, tc[1] - tw / 2, top_z - th],
                                           [tc[0] + tl / 2, tc[1] + tw / 2, top_z]), wood)
    leg = Material("painted", (0.08, 0.08, 0.09), scale_m=0.05, salt=10.0)
    for i, (sx, sy) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
        x = tc[0] + sx * (tl / 2 - 0.06)
        y = tc[1] + sy * (tw / 2 - 0.06)
        add(f"table_leg_{i}", "furniture",
            box_mesh([x - 0.025, y - 0.025, 0.0], [x + 0.025, y + 0.025, top_z - th]), leg)

    # Bookshelf against the north wall (open front: non-convex furniture).
    sx0, sx1, sy0, sy1, sh = -2.1, -1.2, Y - 0.35, Y, 1.8
    shelf_wood = Material("wood", _hsv(0.09, 0.35, 0.75), _hsv(0.08, 0.45, 0.5), 0.06, 11.0)
    panels = [box_mesh([sx0, sy0, 0], [sx0 + 0.02, sy1, sh]), box_mesh([sx1 - 0.02, sy0, 0], [sx1, sy1, sh]),
              box_mesh([sx0, sy1 - 0.01, 0], [sx1, sy1, sh])]
    for z in (0.0, 0.45, 0.9, 1.35, sh - 0.02):
        panels.append(box_mesh([sx0 + 0.02, sy0, z], [sx1 - 0.02, sy1 - 0.01, z + 0.02]))
    add("shelf", "furniture", merge_meshes(panels), shelf_wood)
    books = []
    for z in (0.02, 0.47, 0.92, 1.37):
        x = sx0 + 0.03
        while x < sx1 - 0.12:
            w = rng.uniform(0.025, 0.05)
            hb = rng.uniform(0.2, 0.32)
            books.append(box_mesh([x, sy0 + 0.06, z], [x + w, sy1 - 0.03, z + hb]))
            x += w + 0.003
    add("books", "furniture", merge_meshes(books), Material("books", (0.5, 0.5, 0.5), scale_m=0.035, salt=12.0))

    # Sideboard against the east wall.
    add("sideboard", "furniture", box_mesh([X - 0.45, -1.85, 0.0], [X, -0.85, 0.8]),
        Material("painted", _hsv(rng.uniform(), 0.45, 0.55), scale_m=0.2, salt=13.0))

    # Obstacles on the floor: cardboard boxes and a bin, near walls and corners.
    card = Material("cardboard", (0.55, 0.38, 0.2), (0.45, 0.3, 0.15), 0.1, 14.0)
    for i, (bx, by, size) in enumerate(((-2.05, -1.55, 0.45), (-1.45, -1.7, 0.32), (1.1, 1.55, 0.38))):
        bx += rng.uniform(-0.05, 0.05)
        by += rng.uniform(-0.05, 0.05)
        hgt = size * rng.uniform(0.7, 1.0)
        yaw = rng.uniform(-0.4, 0.4)
        T = make_pose(rotation_z(yaw), [bx, by, 0.0])
        add(f"box_{i}", "obstacle", box_mesh([-size / 2, -size / 2.4, 0], [size / 2, size / 2.4, hgt]), card, T)
    add("bin", "obstacle", cylinder_mesh(0.16, 0.42, 40),
        Material("bands", (0.2, 0.35, 0.25), (0.15, 0.25, 0.2), 0.25, 15.0),
        make_pose(np.eye(3), [-2.1, 0.9 + rng.uniform(-0.1, 0.1), 0.0]))

    # Objects on the table.
    specs = _object_specs(rng)[: config.num_objects]
    placed: list[tuple[np.ndarray, float]] = []
    for obj_id, (name, mesh, mat, r_bound) in enumerate(specs, start=1):
        for _ in range(1000):
            xy = tc + rng.uniform([-tl / 2 + 0.15, -tw / 2 + 0.12], [tl / 2 - 0.15, tw / 2 - 0.12])
            if all(np.linalg.norm(xy - q) > r_bound + rq + 0.03 for q, rq in placed):
                break
        placed.append((xy, r_bound))
        T = make_pose(rotation_z(rng.uniform(-np.pi, np.pi)), [xy[0], xy[1], top_z])
        add(name, "object", mesh, mat, T, obj_id)

    objects_centre = np.array([*np.mean([q for q, _ in placed], axis=0), top_z + 0.08])
    lights = [
        {"pos": [0.0, 0.0, 2.4], "intensity": 1.7, "shadow": True},
        {"pos": [-1.8, 1.2, 2.35], "intensity": 0.5, "shadow": False},
        {"pos": [1.8, -1.5, 2.35], "intensity": 0.4, "shadow": False},
    ]
    return _Layout(parts, top_z, tc, objects_centre, lights, ambient=0.28)


def _object_specs(rng: np.random.Generator) -> list[tuple[str, Mesh, Material, float]]:
    """(name, mesh in object frame with the bottom on z = 0, material, bounding radius in xy)."""
    hues = (rng.uniform() + np.arange(5) / 5.0 + rng.uniform(-0.05, 0.05, 5)) % 1.0
    box = box_mesh([-0.08, -0.03, 0.0], [0.08, 0.03, 0.22])
    can = cylinder_mesh(0.034, 0.115, 48)
    # Non-convex "U" bracket: a base with two uprights (non-overlapping boxes).
    bracket = merge_meshes([box_mesh([-0.09, -0.03, 0.0], [0.09, 0.03, 0.03]),
                            box_mesh([-0.09, -0.03, 0.03], [-0.06, 0.03, 0.11]),
                            box_mesh([0.06, -0.03, 0.03], [0.09, 0.03, 0.11])])
    ball = ellipsoid_mesh([0.055, 0.055, 0.052], 3)
    rock = rock_mesh(0.06, rng, 3)
    return [
        ("cereal_box", box, Material("label", _hsv(hues[0], 0.8, 0.75), _hsv(hues[0] + 0.1, 0.6, 0.35), 0.09, 20.0),
         float(np.hypot(0.08, 0.03))),
        ("soup_can", can, Material("bands", _hsv(hues[1], 0.8, 0.7), _hsv(hues[1] + 0.5, 0.5, 0.8), 0.04, 21.0), 0.034),
        ("bracket", bracket, Material("checker", _hsv(hues[2], 0.85, 0.75), (0.85, 0.85, 0.82), 0.02, 22.0),
         float(np.hypot(0.09, 0.03))),
        ("ball", ball,
         Material("beachball", _hsv(hues[3], 0.85, 0.8), _hsv(hues[3] + 0.33, 0.8, 0.7), 0.05, 23.0), 0.055),
        ("rock", rock, Material("stone", _hsv(hues[4], 0.3, 0.45), _hsv(hues[4], 0.2, 0.25), 0.03, 24.0),
         float(np.linalg.norm(rock.vertices[:, :2], axis=1).max())),
    ]


# ---- the ray-casting model ----------------------------------------------------------------------

class _Model:
    """World-frame triangle soup + per-triangle part index, an Open3D RaycastingScene and shading."""

    def __init__(self, layout: _Layout, seed: int, shadows: bool):
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
        d_cam = _pixel_rays(K)
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
            h * w, hit_idx, alb, E, t_hit, d_cam, R, n, part, self.part_obj_id, _SRGB_LUT, _SRGB_STEPS)
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
        rays = o3c.Tensor(_make_rays(_pixel_rays(K), R, c))
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
def _pixel_rays(K: Intrinsics) -> np.ndarray:
    """(H*W, 3) float64 camera-frame ray directions with z = 1 through the pixel centres (read-only)."""
    u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
    d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], -1).reshape(-1, 3)
    d.setflags(write=False)
    return d


@functools.lru_cache(maxsize=4)
def _model(seed: int, config: SampleSceneConfig) -> _Model:
    return _Model(sample_layout(seed, config), seed, config.shadows)


def render_view(seed: int, config: SampleSceneConfig, T_world_cam: np.ndarray, K: Intrinsics) -> RenderedView:
    """Ray cast the sample room of ``seed`` at ``T_world_cam`` (4x4, OpenCV camera-to-world)."""
    if not isinstance(K, Intrinsics):
        raise TypeError(f"K must be presim.geometry.Intrinsics, got {type(K).__name__}")
    T = np.asarray(T_world_cam, dtype=np.float64)
    # Validate only: the pose is used as given, so a capture pose re-renders bit for bit.
    check_rigid(T, "T_world_cam")
    return _model(int(seed), config).render(T, K)


# ---- trajectory ---------------------------------------------------------------------------------

def capture_trajectory(layout: _Layout, num_frames: int, seed: int) -> np.ndarray:
    """(N, 4, 4) T_world_cam of a hand-held walk: a loop around the room looking at the walls, turning
    to look at the table, then a spiral in for close views of the objects. Equal steps along the path."""
    if num_frames < 2:
        raise ValueError(f"num_frames must be >= 2, got {num_frames}")
    rng = np.random.default_rng([seed, 2])
    s = np.linspace(0.0, 1.0, 4001)
    theta0 = rng.uniform(0, 2 * np.pi)
    theta = theta0 + 2 * np.pi * 1.05 * s
    w = np.clip((s - 0.55) / 0.3, 0, 1)
    w = w * w * (3 - 2 * w)
    room_c = np.array([0.0, 0.0])
    tc = layout.objects_centre[:2]
    centre = (1 - w)[:, None] * room_c + w[:, None] * tc
    rx = (1 - w) * 1.45 + w * 0.8
    ry = (1 - w) * 1.05 + w * 0.8
    xy = centre + np.stack([rx * np.cos(theta), ry * np.sin(theta)], 1)
    ph = rng.uniform(0, 2 * np.pi, 4)
    z = (1 - w) * 1.4 + w * 1.15 + 0.03 * np.sin(2 * np.pi * 3 * s + ph[0])
    pos = np.concatenate([xy, z[:, None]], 1)
    # Equal arc-length steps.
    seg = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    targets = np.linspace(0, arc[-1], num_frames)
    idx = np.searchsorted(arc, targets).clip(0, len(s) - 1)
    s_f, theta_f, pos_f = s[idx], theta[idx], pos[idx]

    # Look direction: yaw from "outward + a bit forward" (walls) to "at the objects" (a = 1),
    # turning through the walking direction so the rotation is continuous.
    ramp = np.clip((s_f - 0.3) / 0.5, 0, 1)
    a = 0.4 + 0.6 * ramp * ramp * (3 - 2 * ramp)
    to_obj = layout.objects_centre[None, :] - pos_f
    yaw_obj = np.arctan2(to_obj[:, 1], to_obj[:, 0])
    d = np.mod(yaw_obj - theta_f, 2 * np.pi)
    yaw = theta_f + a * d
    pitch_out = np.arctan2(1.0 - pos_f[:, 2], 2.0)
    pitch_in = np.arctan2(to_obj[:, 2], np.linalg.norm(to_obj[:, :2], axis=1))
    pitch = (1 - a) * pitch_out + a * pitch_in
    pitch += np.radians(2.0) * np.sin(2 * np.pi * 2 * s_f + ph[1])
    roll = np.radians(2.0) * np.sin(2 * np.pi * 2.5 * s_f + ph[2])
    out = np.empty((num_frames, 4, 4))
    for i in range(num_frames):
        f = np.array([np.cos(pitch[i]) * np.cos(yaw[i]), np.cos(pitch[i]) * np.sin(yaw[i]), np.sin(pitch[i])])
        T = look_at(pos_f[i], pos_f[i] + f)
        out[i] = compose(T, make_pose(rotation_z(roll[i]), np.zeros(3)))
    return out


# ---- depth corruption ---------------------------------------------------------------------------

def corrupt_depth(depth_m: np.ndarray, albedo_lum: np.ndarray, cos_incidence: np.ndarray,
                  config: SampleSceneConfig, rng: np.random.Generator) -> np.ndarray:
    """A realistic sensor reading of the exact depth ``depth_m`` (float32 (H, W), 0 = none).

    In this order: foreground dilation at depth edges (``edge_dilate_px``), holes left of nearer
    surfaces (projector shadow, ``edge_shadow_px``), on dark surfaces (``dark_albedo``,
    ``dark_dropout``), at grazing incidence (``grazing_deg``) and random speckles; Gaussian noise with
    ``sigma = noise_sigma0_m + noise_k_per_m * z^2``; no depth outside ``[min_range_m, max_range_m]``;
    finally the whole map is shifted by
    ``shift_px`` relative to the color (registration error), vacated borders are 0.
    """
    import cv2

    d = np.asarray(depth_m, dtype=np.float32)
    if d.ndim != 2 or albedo_lum.shape != d.shape or cos_incidence.shape != d.shape:
        raise ValueError(f"depth, albedo and incidence must be (H, W) of one shape, got "
                         f"{d.shape}, {albedo_lum.shape}, {cos_incidence.shape}")
    valid = d > 0
    big = np.where(valid, d, np.float32(1e3))
    kernel = np.ones((3, 3), np.uint8)
    dmin = cv2.erode(big, kernel)
    # A depth edge: a 3x3 neighbour is closer by more than 4 % of the depth (or 5 cm).
    far_side = valid & (big - dmin > np.maximum(0.04 * big, 0.05))
    out = d.copy()
    if config.edge_dilate_px > 0:
        k = np.ones((2 * config.edge_dilate_px + 1,) * 2, np.uint8)
        grown = cv2.erode(big, k)
        band = cv2.dilate(far_side.astype(np.uint8), k).astype(bool) & valid
        take = band & (grown < big - np.maximum(0.04 * big, 0.05))
        out[take] = grown[take]
    drop = np.zeros(d.shape, bool)
    if config.edge_shadow_px > 0:
        # The IR projector sits to the right of the camera: background up to edge_shadow_px pixels to
        # the LEFT of a nearer surface is not lit by the pattern (one-sided holes, like a Kinect).
        W = config.edge_shadow_px
        right_min = cv2.erode(big, np.ones((1, W + 1), np.uint8), anchor=(0, 0),
                              borderType=cv2.BORDER_CONSTANT, borderValue=1e3)
        shadow = valid & (d - right_min > np.maximum(0.04 * d, 0.05))
        drop |= shadow & (rng.random(d.shape) < 0.8)
    drop |= (albedo_lum < config.dark_albedo) & (rng.random(d.shape) < config.dark_dropout)
    ang = np.degrees(np.arccos(np.clip(cos_incidence, 0, 1)))
    p_graze = np.clip((ang - (config.grazing_deg - 6.0)) / 12.0, 0, 1)
    drop |= rng.random(d.shape) < p_graze
    drop |= rng.random(d.shape) < config.speckle_dropout
    noise = rng.standard_normal(d.shape).astype(np.float32)
    out = out + noise * (config.noise_sigma0_m + config.noise_k_per_m * out * out)
    drop |= (out < config.min_range_m) | (out > config.max_range_m)
    out[drop | ~(out > 0)] = 0.0
    du, dv = config.shift_px
    shifted = np.zeros_like(out)
    h, w = out.shape
    shifted[max(dv, 0):h + min(dv, 0), max(du, 0):w + min(du, 0)] = \
        out[max(-dv, 0):h + min(-dv, 0), max(-du, 0):w + min(-du, 0)]
    return shifted.astype(np.float32)


# ---- build / load -------------------------------------------------------------------------------

def _intrinsics(config: SampleSceneConfig) -> Intrinsics:
    return Intrinsics.from_fov(config.width, config.height, config.hfov_deg)


def _check_config(config: SampleSceneConfig) -> None:
    if not 3 <= config.num_objects <= 5:
        raise ValueError(f"num_objects must be 3..5, got {config.num_objects}")
    if config.width < 16 or config.height < 16:
        raise ValueError(f"image size must be at least 16x16, got {config.width}x{config.height}")
    if config.num_frames < 2:
        raise ValueError(f"num_frames must be >= 2, got {config.num_frames}")


def _config_to_dict(config: SampleSceneConfig) -> dict:
    d = dataclasses.asdict(config)
    d["shift_px"] = list(config.shift_px)
    return d


def _config_from_dict(d: dict, where: Path) -> SampleSceneConfig:
    names = {f.name for f in dataclasses.fields(SampleSceneConfig)}
    unknown = set(d) - names
    if unknown:
        raise SceneError(f"{where}: unknown sample-scene config fields {sorted(unknown)}")
    d = dict(d)
    if "shift_px" in d:
        d["shift_px"] = tuple(int(x) for x in d["shift_px"])
    return SampleSceneConfig(**d)


def build_sample_scene(dst: str | Path, seed: int = 0, config: SampleSceneConfig = SampleSceneConfig(),
                       overwrite: bool = False) -> Path:
    """Build the sample scene for ``seed`` into the folder ``dst`` (atomically) and return ``dst``.

    The folder is a saved scene (:func:`presim.capture.store.load_scene`) whose depth is the corrupted
    sensor depth, plus ``dst/ground_truth/`` (exact depth, object masks, room mesh, parts, config).
    """
    from presim.capture.store import fuse_point_cloud, save_scene

    _check_config(config)
    dst = Path(dst)
    if dst.exists() and not overwrite:
        raise FileExistsError(f"{dst}: already exists (pass overwrite to replace it)")
    model = _model(int(seed), config)
    layout = model.layout
    K = _intrinsics(config)
    T_world_cams = capture_trajectory(layout, config.num_frames, seed)
    n, h, w = config.num_frames, config.height, config.width
    color = np.empty((n, h, w, 3), np.uint8)
    depth_clean = np.empty((n, h, w), np.float32)
    depth_raw = np.empty((n, h, w), np.float32)
    obj_id = np.empty((n, h, w), np.uint8)
    def render_frame(i: int) -> int:
        view = model.render(T_world_cams[i], K)
        color[i] = view.color
        depth_clean[i] = view.depth_m
        obj_id[i] = view.object_id
        depth_raw[i] = corrupt_depth(view.depth_m, view.albedo_lum, view.cos_incidence, config,
                                     np.random.default_rng([seed, 3, i]))
        return i

    # Frames are independent (per-frame random streams), so two threads render them in any order
    # with identical results; ray casting, numba kernels and most numpy work release the GIL.
    with ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as pool:
        for _ in progress(pool.map(render_frame, range(n)), total=n, desc="rendering sample scene", unit="frame"):
            pass

    frame_ids = [f"frame-{i:06d}" for i in range(n)]
    stamps = np.arange(n) / config.frame_rate_hz
    clean = Scene(frame_ids, stamps, T_world_cams, [K] * n, ArrayFrameSource(color, depth_clean),
                  SceneMeta("", "sample"))
    # The point cloud is fused from the exact depth (the scene's ground-truth geometry).
    points = fuse_point_cloud(clean, voxel_m=0.01, stride=6)
    on_floor = float(np.mean(np.abs(points.xyz[:, 2]) < 0.01)) if len(points) else 0.0

    with atomic_dir(dst, overwrite=overwrite) as tmp:
        models = tmp / "_models"
        models.mkdir()
        objects = []
        for k, p in enumerate(layout.parts):
            if p.obj_id == 0:
                continue
            path = models / f"{p.name}.ply"
            _write_part_ply(path, p.mesh, p.material, model.noise)
            sym = p.name in ("soup_can", "ball")  # solids of revolution about their z axis
            objects.append(SceneObject(p.obj_id, p.name, p.T_world_part.copy(), str(path),
                                       symmetric=sym, symmetry_axis=(0.0, 0.0, 1.0) if sym else None))
        meta = SceneMeta(
            source=f"sample-scene seed={seed}", source_format="sample", importer_version=str(SAMPLE_VERSION),
            notes=("procedural room rendered by ray casting (presim.capture.sample_scene)",
                   "depth.npy is corrupted like a real sensor; exact depth in ground_truth/depth_clean.npy",
                   "point cloud fused from the exact depth"),
        )
        scene = Scene(frame_ids, stamps, T_world_cams, [K] * n, ArrayFrameSource(color, depth_raw), meta,
                      points=points, floor=FloorPlane((0.0, 0.0, 1.0), 0.0, on_floor),
                      gravity_world=np.array([0.0, 0.0, -1.0]), objects=objects)
        inner = save_scene(scene, tmp / "scene")
        for entry in inner.iterdir():
            os.replace(entry, tmp / entry.name)
        inner.rmdir()
        shutil.rmtree(models)

        gt = tmp / GT_DIR
        gt.mkdir()
        np.save(gt / "depth_clean.npy", depth_clean)
        np.save(gt / "object_id.npy", obj_id)
        _write_room_ply(gt / "room.ply", model)
        parts = []
        for k, p in enumerate(layout.parts):
            a, b = model.part_ranges[k]
            v = model.vertices[model.triangles[a:b].reshape(-1)]
            parts.append({"name": p.name, "kind": p.kind, "obj_id": p.obj_id,
                          "aabb_min": v.min(0).astype(float).round(6).tolist(),
                          "aabb_max": v.max(0).astype(float).round(6).tolist(),
                          "tri_start": int(a), "tri_end": int(b)})
        atomic_write_json(gt / "parts.json", {"parts": parts}, indent=1)
        atomic_write_json(gt / "sample.json", {
            "format": "presim-sample-scene", "version": SAMPLE_VERSION, "seed": int(seed),
            "config": _config_to_dict(config), "table_top_z_m": layout.table_top_z_m,
            "lights": layout.lights, "ambient": layout.ambient,
        })
    return dst


def _write_part_ply(path: Path, mesh: Mesh, mat: Material, noise: NoiseField) -> None:
    rgb = srgb_encode(albedo(mat, mesh.vertices, mesh.normals, noise))
    write_ply(path, mesh.vertices, mesh.triangles, colors=rgb, normals=mesh.normals)


def _write_room_ply(path: Path, model: _Model) -> None:
    """Whole scene in world metres; vertex colors = albedo at the vertices (flat parts keep one
    color per corner, so the PLY is a coarse preview of the texture, not the texture itself)."""
    rgb = np.zeros((len(model.vertices), 3), np.uint8)
    v_part = np.zeros(len(model.vertices), np.int64)
    v_part[model.triangles.reshape(-1)] = np.repeat(model.tri_part, 3)
    for k, p in enumerate(model.layout.parts):
        sel = v_part == k
        Tpw = model.T_part_world[k]
        pl = model.vertices[sel].astype(np.float64) @ Tpw[:3, :3].T + Tpw[:3, 3]
        nl = model.vertex_normals[sel].astype(np.float64) @ Tpw[:3, :3].T
        rgb[sel] = srgb_encode(albedo(p.material, pl, nl, model.noise))
    write_ply(path, model.vertices, model.triangles, colors=rgb, normals=model.vertex_normals)


@functools.lru_cache(maxsize=16)
def _read_sample_json(path_str: str, mtime_ns: int) -> tuple[int, SampleSceneConfig, float]:
    p = Path(path_str)
    try:
        d = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise SceneError(f"{p}: corrupt JSON ({e})") from e
    if d.get("format") != "presim-sample-scene":
        raise SceneError(f"{p}: not a sample-scene description")
    if d.get("version") != SAMPLE_VERSION:
        raise SceneError(f"{p}: sample-scene version {d.get('version')} is not supported (this PreSim "
                         f"reads version {SAMPLE_VERSION}); rebuild it with `presim sample-scene`")
    return int(d["seed"]), _config_from_dict(d["config"], p), float(d["table_top_z_m"])


def _sample_info(dst: Path) -> tuple[int, SampleSceneConfig, float]:
    p = Path(dst) / GT_DIR / "sample.json"
    if not p.is_file():
        raise FileNotFoundError(f"{p}: not found; {dst} is not a sample scene built by `presim sample-scene`")
    return _read_sample_json(str(p.resolve()), p.stat().st_mtime_ns)


def load_sample_ground_truth(dst: str | Path) -> SampleGroundTruth:
    """Ground truth of the sample scene at ``dst`` (exact depth and object masks memory-mapped)."""
    dst = Path(dst)
    seed, config, top_z = _sample_info(dst)
    gt = dst / GT_DIR
    for name in ("depth_clean.npy", "object_id.npy", "room.ply", "parts.json"):
        if not (gt / name).is_file():
            raise FileNotFoundError(f"{gt / name}: missing from the sample scene's ground truth")
    depth = np.load(gt / "depth_clean.npy", mmap_mode="r")
    obj = np.load(gt / "object_id.npy", mmap_mode="r")
    shape = (config.num_frames, config.height, config.width)
    if depth.shape != shape or depth.dtype != np.float32:
        raise SceneError(f"{gt / 'depth_clean.npy'}: expected float32 {shape}, got {depth.dtype} {depth.shape}")
    if obj.shape != shape:
        raise SceneError(f"{gt / 'object_id.npy'}: expected {shape}, got {obj.shape}")
    parts = tuple(SamplePart(p["name"], p["kind"], int(p["obj_id"]), tuple(p["aabb_min"]), tuple(p["aabb_max"]),
                             int(p["tri_start"]), int(p["tri_end"]))
                  for p in json.loads((gt / "parts.json").read_text())["parts"])
    return SampleGroundTruth(dst, seed, config, depth, obj, gt / "room.ply", parts, top_z)


def clean_scene(dst: str | Path):
    """The sample scene at ``dst`` with its frames reading the exact depth instead of the sensor depth."""
    from presim.capture.store import load_scene

    scene = load_scene(dst)
    gt = load_sample_ground_truth(dst)
    color = scene.frames.color  # memmap of color.npy
    return dataclasses.replace(scene, frames=ArrayFrameSource(color, gt.depth_clean_m))


def render_object_silhouettes(dst: str | Path, T_world_cam: np.ndarray, K: Intrinsics
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each table object of the sample scene at ``dst`` ray cast ALONE (no occluders) at any pose.

    Returns ``(obj_ids int32 (K,), masks bool (K, H, W), depth_m float32 (K, H, W))``: the full
    silhouettes and depths (BOP ``mask``, as opposed to the visible ``mask_visib`` that
    :func:`render_ground_truth`'s object ids give), with ``depth_m`` equal to the scene depth wherever
    the object is visible.
    """
    seed, config, _ = _sample_info(Path(dst))
    if not isinstance(K, Intrinsics):
        raise TypeError(f"K must be presim.geometry.Intrinsics, got {type(K).__name__}")
    T = np.asarray(T_world_cam, dtype=np.float64)
    check_rigid(T, "T_world_cam")
    return _model(int(seed), config).object_silhouettes(T, K)


def render_ground_truth(dst: str | Path, T_world_cam: np.ndarray, K: Intrinsics
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray cast the true geometry of the sample scene at ``dst`` at any pose.

    Args:
        dst: a folder written by :func:`build_sample_scene`.
        T_world_cam: 4x4 OpenCV camera-to-world pose.
        K: intrinsics (any resolution).

    Returns:
        ``(color uint8 (H,W,3), depth_m float32 (H,W) exact z-depth with 0 = nothing,
        object_id int32 (H,W) with 0 = background)`` -- the same shading as the captured frames, so at
        a capture pose this equals the stored color and clean depth exactly. The ray-casting scene
        is built once per process per (seed, config).
    """
    seed, config, _ = _sample_info(Path(dst))
    view = render_view(seed, config, T_world_cam, K)
    return view.color, view.depth_m, view.object_id
