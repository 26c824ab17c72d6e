"""Building a sample scene folder (atomically) and reading its ground truth back.

``DST`` is a saved scene (:func:`presim.capture.store.load_scene`) plus ``DST/ground_truth/``
(exact depth, object masks, room mesh, parts, seed + config); see docs/sample-scene.md.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import shutil
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from presim.capture.procedural import Material, Mesh, NoiseField, albedo, srgb_encode
from presim.formats.ply import write_ply
from presim.capture.sample_scene.config import SampleSceneConfig
from presim.capture.sample_scene.corrupt import corrupt_depth
from presim.capture.sample_scene.layout import capture_trajectory
from presim.capture.sample_scene.render import SceneRaycaster, render_view, scene_raycaster
from presim.capture.scene import ArrayFrameSource, FloorPlane, Scene, SceneError, SceneMeta, SceneObject
from presim.capture.store import fuse_point_cloud, load_scene, save_scene
from presim.geometry import Intrinsics, check_rigid
from presim.io_utils import atomic_dir, atomic_write_json, progress

__all__ = [
    "SAMPLE_VERSION", "GT_DIR", "SamplePart", "SampleGroundTruth", "build_sample_scene",
    "load_sample_ground_truth", "clean_scene", "render_ground_truth", "render_object_silhouettes",
]

SAMPLE_VERSION = 1
GT_DIR = "ground_truth"


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
    _check_config(config)
    dst = Path(dst)
    if dst.exists() and not overwrite:
        raise FileExistsError(f"{dst}: already exists (pass overwrite to replace it)")
    model = scene_raycaster(int(seed), config)
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


def _write_room_ply(path: Path, model: SceneRaycaster) -> None:
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
    return scene_raycaster(int(seed), config).object_silhouettes(T, K)


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
