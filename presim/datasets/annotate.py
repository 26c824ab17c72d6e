"""Per-frame annotation: render each object model at its pose, compare with the scene's depth.

For every object instance in a frame this gives exactly what BOP's ``calc_gt_info`` defines:

- **mask** (``mask/``): silhouette of the model rendered alone at its pose (inside the image).
- **mask_visib** (``mask_visib/``): the part of the silhouette that is visible: the model's distance
  (ray length) is not more than ``visib_tolerance_m`` behind the scene's distance, or the scene
  has no depth there (BOP'19 rule ``visib_mode='bop19'``, delta = 15 mm). PreSim also knows every
  object model, so an instance hidden behind another *object model* is marked occluded exactly
  (``object_occlusion``), whatever the synthesized depth says.
- **px_count_all**: silhouette pixels on a canvas three times the image size (BOP counts the
  truncated part outside the image too), **px_count_valid**: silhouette pixels inside the image
  with valid scene depth, **px_count_visib**: visible pixels, **visib_fract** = visib / all.
- **bbox_obj**: tight box ``[x, y, w, h]`` of the whole (untruncated) silhouette with
  ``w = x_max - x_min`` (bop_toolkit ``calc_2d_bbox``), ``[-1, -1, -1, -1]`` when nothing is
  visible (as bop_toolkit writes it); **bbox_visib**: box of the visible mask.

Rasterization is a z-buffer at pixel centres with perspective-correct depth (numba), checked
against an exact ray cast (Open3D ``RaycastingScene``, :func:`render_model_depth_reference`).
Point-cloud models (thesis §5.3.5) are splatted to their nearest pixel and their holes closed with
the renderer's switching median filter (:func:`presim.synthesis.cracks.crack_filter`, thesis
eq. 3.9: a zero pixel whose 3x3 window is more than half set takes the *lower* median of the set
pixels).

Each instance's result is one :class:`InstanceAnnotation`: the BOP records
:class:`~presim.formats.bop.GtInstance` (``scene_gt``) and :class:`~presim.formats.bop.GtInfo`
(``scene_gt_info``) plus the two masks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import cv2
import numba
import numpy as np

from presim.datasets.objects import ObjectModel
from presim.formats.bop import GtInfo, GtInstance
from presim.geometry import Intrinsics, check_rigid, project, transform_points
from presim.synthesis.cracks import crack_filter

__all__ = ["AnnotateConfig", "ModelRender", "InstanceAnnotation", "render_model_depth",
           "render_model_depth_reference", "annotate_instances", "bbox_from_mask", "ray_norm_image"]


@dataclass(frozen=True)
class AnnotateConfig:
    """How annotations are computed (defaults = BOP'19 ``calc_gt_info``)."""

    visib_tolerance_m: float = 0.015
    """BOP's ``delta``: a model pixel stays visible while its distance is at most this much behind the
    scene's distance (metres)."""
    near_m: float = 0.01
    """Triangles with a vertex closer than this to the camera plane are not drawn (BOP's renderer
    clips at 10 mm)."""
    canvas_factor: int = 3
    """The silhouette is rendered on a canvas this many times the image size (centred on the image)
    so that px_count_all and bbox_obj include truncated parts, as bop_toolkit does."""
    object_occlusion: bool = True
    """Also occlude an instance where another instance's model is in front (exact; off = BOP's
    depth-only test)."""
    point_fill_iters: int = 2
    """Switching-median passes closing holes of splatted point-cloud models."""
    backend: str = "numba"
    """``"numba"`` z-buffer rasterizer or ``"open3d"`` ray casting (reference, meshes only)."""
    occlusion_open_px: int = 2
    """Remove scene-depth occlusions thinner than about 2 x this many pixels (morphological opening)
    before they hide model pixels: slivers along silhouettes come from depth noise, misregistration
    and edge bleeding of synthesized depth, real occluders are wider. 0 = BOP's per-pixel test.
    (Occlusion between the known object models is exact and not opened.)"""
    pixel_offset_px: float = 0.0
    """Shift of the rendered silhouette in u and v, pixels. 0 = PreSim's convention (pixel centres at
    integers, as the synthesized images). -0.5 reproduces bop_toolkit's OpenGL renderer, whose
    masks and boxes sit half a pixel up-left of the same K (LM-O bbox_obj IoU 0.972 -> 0.9999)."""


@dataclass(frozen=True)
class ModelRender:
    """Depth of one model rendered alone on (a crop of) the large canvas."""

    depth_m: np.ndarray
    """float32 (h, w) z-depth, 0 = not covered."""
    u0: int
    """Image column of ``depth_m[:, 0]`` (may be negative: the canvas extends beyond the image)."""
    v0: int
    """Image row of ``depth_m[0, :]``."""

    def in_image(self, K: Intrinsics) -> np.ndarray:
        """The part inside the image as a full (H, W) float32 depth map."""
        out = np.zeros((K.height, K.width), np.float32)
        h, w = self.depth_m.shape
        ua, ub = max(self.u0, 0), min(self.u0 + w, K.width)
        va, vb = max(self.v0, 0), min(self.v0 + h, K.height)
        if ua < ub and va < vb:
            out[va:vb, ua:ub] = self.depth_m[va - self.v0:vb - self.v0, ua - self.u0:ub - self.u0]
        return out


@dataclass(frozen=True)
class InstanceAnnotation:
    """Annotations of one object instance in one image: its BOP rows and its masks."""

    gt: GtInstance
    """``scene_gt.json`` row: object id and model-to-camera pose (metres)."""
    info: GtInfo
    """``scene_gt_info.json`` row: boxes, pixel counts, visible fraction."""
    mask: np.ndarray
    """bool (H, W) full silhouette inside the image."""
    mask_visib: np.ndarray
    """bool (H, W) visible part."""

    @property
    def obj_id(self) -> int:
        return self.gt.obj_id

    @property
    def visib_fract(self) -> float:
        return self.info.visib_fract

    def gt_dict(self) -> dict:
        """``scene_gt.json`` entry (:meth:`GtInstance.to_json`)."""
        return self.gt.to_json()

    def gt_info_dict(self) -> dict:
        """``scene_gt_info.json`` entry (:meth:`GtInfo.to_json`)."""
        return self.info.to_json()


# ---- rasterization ------------------------------------------------------------------------------

@numba.njit(cache=True)
def _raster_mesh(u, v, z, faces, u0, v0, out, near):  # pragma: no cover - compiled
    """Z-buffer triangles (pixel coords u, v, depth z per vertex) into ``out`` whose pixel (0, 0) is
    image pixel (u0, v0). Depth is perspective-correct (1/z is affine in screen space)."""
    ch, cw = out.shape
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        za, zb, zc = z[a], z[b], z[c]
        if za <= near or zb <= near or zc <= near:
            continue
        ua, va, ub, vb, uc, vc = u[a], v[a], u[b], v[b], u[c], v[c]
        area = (ub - ua) * (vc - va) - (vb - va) * (uc - ua)
        if area == 0.0 or not np.isfinite(area):
            continue
        sgn = 1.0 if area > 0 else -1.0
        inv_area = 1.0 / abs(area)
        x_lo = max(int(np.ceil(min(ua, ub, uc))), u0)
        x_hi = min(int(np.floor(max(ua, ub, uc))), u0 + cw - 1)
        y_lo = max(int(np.ceil(min(va, vb, vc))), v0)
        y_hi = min(int(np.floor(max(va, vb, vc))), v0 + ch - 1)
        iza, izb, izc = 1.0 / za, 1.0 / zb, 1.0 / zc
        for y in range(y_lo, y_hi + 1):
            py = float(y)
            for x in range(x_lo, x_hi + 1):
                px = float(x)
                w0 = sgn * ((uc - ub) * (py - vb) - (vc - vb) * (px - ub))
                w1 = sgn * ((ua - uc) * (py - vc) - (va - vc) * (px - uc))
                w2 = sgn * ((ub - ua) * (py - va) - (vb - va) * (px - ua))
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                iz = (w0 * iza + w1 * izb + w2 * izc) * inv_area
                if iz <= 0.0:
                    continue
                d = 1.0 / iz
                cur = out[y - v0, x - u0]
                if cur == 0.0 or d < cur:
                    out[y - v0, x - u0] = d


@numba.njit(cache=True)
def _splat_points(u, v, z, u0, v0, out, near):  # pragma: no cover - compiled
    ch, cw = out.shape
    for i in range(u.shape[0]):
        if z[i] <= near or not np.isfinite(u[i]) or not np.isfinite(v[i]):
            continue
        x = int(np.floor(u[i] + 0.5)) - u0
        y = int(np.floor(v[i] + 0.5)) - v0
        if x < 0 or y < 0 or x >= cw or y >= ch:
            continue
        cur = out[y, x]
        if cur == 0.0 or z[i] < cur:
            out[y, x] = z[i]


def _canvas_crop(uv: np.ndarray, ok: np.ndarray, K: Intrinsics, factor: int) -> tuple[int, int, int, int] | None:
    """Crop (u0, v0, w, h) of the large canvas covering the projected points, None if empty."""
    if not ok.any():
        return None
    pad_u, pad_v = K.width * (factor - 1) // 2, K.height * (factor - 1) // 2
    cu0, cv0, cu1, cv1 = -pad_u, -pad_v, K.width + pad_u - 1, K.height + pad_v - 1
    uu, vv = uv[ok, 0], uv[ok, 1]
    u0 = max(int(np.floor(uu.min())) - 1, cu0)
    v0 = max(int(np.floor(vv.min())) - 1, cv0)
    u1 = min(int(np.ceil(uu.max())) + 1, cu1)
    v1 = min(int(np.ceil(vv.max())) + 1, cv1)
    if u1 < u0 or v1 < v0:
        return None
    return u0, v0, u1 - u0 + 1, v1 - v0 + 1


def _project_model(model: ObjectModel, T_cam_obj: np.ndarray, K: Intrinsics, config: AnnotateConfig):
    """Model points in the camera frame (V, 3), their pixel coordinates (V, 2) and the canvas crop
    ``(u0, v0, w, h)`` they cover (None: nothing in front of the camera)."""
    p = transform_points(np.asarray(T_cam_obj, dtype=np.float64), model.vertices_m.astype(np.float64))
    uv = project(K, p)[0] + config.pixel_offset_px
    return p, uv, _canvas_crop(uv, p[:, 2] > config.near_m, K, config.canvas_factor)


def render_model_depth(model: ObjectModel, T_cam_obj: np.ndarray, K: Intrinsics,
                       config: AnnotateConfig = AnnotateConfig()) -> ModelRender:
    """Render ``model`` alone at pose ``T_cam_obj`` (4x4, metres) with intrinsics ``K``.

    Returns the z-depth (metres) of the crop of the ``canvas_factor``-times larger canvas that the
    model covers; ``ModelRender.in_image(K)`` gives the (H, W) part inside the image.
    """
    if config.backend == "open3d":
        return render_model_depth_reference(model, T_cam_obj, K, config)
    if config.backend != "numba":
        raise ValueError(f"unknown annotation backend {config.backend!r} (use 'numba' or 'open3d')")
    p, uv, crop = _project_model(model, T_cam_obj, K, config)
    if crop is None:
        return ModelRender(np.zeros((0, 0), np.float32), 0, 0)
    z = p[:, 2]
    u0, v0, w, h = crop
    out = np.zeros((h, w), np.float32)
    u = np.ascontiguousarray(uv[:, 0])
    v = np.ascontiguousarray(uv[:, 1])
    if model.faces is not None:
        _raster_mesh(u, v, np.ascontiguousarray(z), model.faces, u0, v0, out, config.near_m)
    else:
        _splat_points(u, v, np.ascontiguousarray(z), u0, v0, out, config.near_m)
        if config.point_fill_iters > 0:
            color = np.zeros(out.shape + (3,), np.uint8)  # depth only: the filter carries colour along
            for _ in range(config.point_fill_iters):
                out, color = crack_filter(out, color, "switching_median", 3)
    return ModelRender(out, u0, v0)


def render_model_depth_reference(model: ObjectModel, T_cam_obj: np.ndarray, K: Intrinsics,
                                 config: AnnotateConfig = AnnotateConfig()) -> ModelRender:
    """Exact ray cast of a mesh model through every pixel centre of the large canvas (Open3D).

    Slow and obviously correct: the reference the numba rasterizer is tested against.
    """
    import open3d as o3d

    if model.faces is None:
        raise ValueError(f"model {model.obj_id}: the ray-cast reference needs a mesh, not a point cloud")
    p, uv, crop = _project_model(model, T_cam_obj, K, config)
    if crop is None:
        return ModelRender(np.zeros((0, 0), np.float32), 0, 0)
    z = p[:, 2]
    u0, v0, w, h = crop
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(p.astype(np.float32)), o3d.core.Tensor(model.faces.astype(np.uint32)))
    uu, vv = np.meshgrid(np.arange(u0, u0 + w, dtype=np.float64), np.arange(v0, v0 + h, dtype=np.float64))
    # Direction with unit z: the hit distance t is then the z-depth itself.
    off = config.pixel_offset_px
    dirs = np.stack([(uu - off - K.cx) / K.fx, (vv - off - K.cy) / K.fy, np.ones_like(uu)], axis=-1)
    rays = np.concatenate([np.zeros_like(dirs), dirs], axis=-1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    depth = np.where(np.isfinite(t) & (t > config.near_m), t, 0.0).astype(np.float32)
    return ModelRender(depth, u0, v0)


# ---- boxes and masks ----------------------------------------------------------------------------

def bbox_from_mask(mask: np.ndarray, u0: int = 0, v0: int = 0) -> tuple[int, int, int, int]:
    """BOP box ``[x, y, w, h]`` of a boolean mask whose pixel (0, 0) is image pixel (u0, v0);
    ``w = x_max - x_min`` as bop_toolkit's ``calc_2d_bbox``; ``(-1, -1, -1, -1)`` if empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return (-1, -1, -1, -1)
    x0, y0 = int(xs.min()) + u0, int(ys.min()) + v0
    return (x0, y0, int(xs.max()) + u0 - x0, int(ys.max()) + v0 - y0)


_RAY_NORM_CACHE: dict[tuple, np.ndarray] = {}


def ray_norm_image(K: Intrinsics) -> np.ndarray:
    """(H, W) float64 ratio distance / z-depth of each pixel centre (cached per intrinsics)."""
    key = (K.fx, K.fy, K.cx, K.cy, K.width, K.height)
    r = _RAY_NORM_CACHE.get(key)
    if r is None:
        u = (np.arange(K.width) - K.cx) / K.fx
        v = (np.arange(K.height) - K.cy) / K.fy
        r = np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1.0)
        if len(_RAY_NORM_CACHE) > 8:
            _RAY_NORM_CACHE.clear()
        _RAY_NORM_CACHE[key] = r
    return r


def annotate_instances(models: Mapping[int, ObjectModel], instances: Sequence[tuple[int, np.ndarray]],
                       K: Intrinsics, scene_depth_m: np.ndarray | None, scene_valid: np.ndarray | None = None,
                       config: AnnotateConfig = AnnotateConfig()) -> list[InstanceAnnotation]:
    """Annotate object instances in one image.

    Args:
        models: ``obj_id -> ObjectModel``.
        instances: ``(obj_id, T_cam_obj)`` per instance (4x4, metres), in output order.
        K: intrinsics of the image (H = K.height, W = K.width).
        scene_depth_m: float32 (H, W) z-depth of the scene (synthesized or captured), 0 = unknown;
            None = no depth (every silhouette pixel counts as visible unless another model hides it).
        scene_valid: optional bool (H, W): pixels whose depth is a measurement/synthesis (False =
            filled or unknown: treated as no depth, BOP's ``d_test == 0``).
        config: see :class:`AnnotateConfig`.

    Returns:
        One :class:`InstanceAnnotation` per instance, in the order given.
    """
    H, W = K.height, K.width
    if scene_depth_m is not None:
        scene_depth_m = np.asarray(scene_depth_m)
        if scene_depth_m.shape != (H, W):
            raise ValueError(f"scene depth shape {scene_depth_m.shape} != intrinsics {H}x{W}")
    if scene_valid is not None and np.asarray(scene_valid).shape != (H, W):
        raise ValueError(f"scene valid mask shape {np.asarray(scene_valid).shape} != intrinsics {H}x{W}")
    for obj_id, _ in instances:
        if int(obj_id) not in models:
            raise ValueError(f"no model for obj_id {obj_id} (models: {sorted(models)})")

    renders = []
    depths_in = []
    for obj_id, T in instances:
        # Validate only (the pose is stored unchanged); real GT (LM-O) is orthonormal to ~2e-3.
        check_rigid(T, f"pose of object {obj_id}", tol=1e-2)
        T = np.array(T, dtype=np.float64)
        r = render_model_depth(models[int(obj_id)], T, K, config)
        renders.append((int(obj_id), T, r))
        depths_in.append(r.in_image(K))

    ray_norm = ray_norm_image(K)
    if scene_depth_m is not None:
        scene_ok = scene_depth_m > 0
        if scene_valid is not None:
            scene_ok &= np.asarray(scene_valid, dtype=bool)
        dist_scene = scene_depth_m.astype(np.float64) * ray_norm
    if config.object_occlusion and depths_in:
        stack = np.stack([np.where(d > 0, d, np.inf) for d in depths_in])
        front = stack.min(axis=0)

    out = []
    for (obj_id, T, r), d in zip(renders, depths_in):
        mask = d > 0
        visib = mask.copy()
        if scene_depth_m is not None:
            dist_model = d.astype(np.float64) * ray_norm
            # bop19: visible where the model is not behind the scene by more than delta, or no depth.
            occluded = mask & scene_ok & (dist_model - dist_scene > config.visib_tolerance_m)
            if config.occlusion_open_px > 0 and occluded.any():
                rad = int(config.occlusion_open_px)
                kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))
                occluded = cv2.morphologyEx(occluded.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)
            visib &= ~occluded
            px_valid = int(np.count_nonzero(mask & scene_ok))
        else:
            px_valid = 0
        if config.object_occlusion and len(depths_in) > 1:
            visib &= d <= front
        px_all = int(np.count_nonzero(r.depth_m))
        px_visib = int(np.count_nonzero(visib))
        visib_fract = px_visib / px_all if px_all > 0 else 0.0
        # bop_toolkit leaves bbox_obj at -1 when nothing of the object is visible.
        bbox_obj = bbox_from_mask(r.depth_m > 0, r.u0, r.v0) if px_visib > 0 else (-1, -1, -1, -1)
        info = GtInfo(bbox_obj=bbox_obj, bbox_visib=bbox_from_mask(visib), px_count_all=px_all,
                      px_count_valid=px_valid, px_count_visib=px_visib, visib_fract=float(visib_fract))
        out.append(InstanceAnnotation(GtInstance.from_pose(obj_id, T), info, mask, visib))
    return out
