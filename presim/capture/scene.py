"""The one scene type every capture format is read into.

A :class:`Scene` is an ordered list of RGB-D frames (color uint8 HxWx3, depth float32 metres HxW with
0 = invalid, per-frame intrinsics, ``T_world_cam``, timestamp, frame id) plus a colored point cloud of
the whole scene, the floor plane / gravity when known, objects with meshes and world poses (sample
scene, BOP, YCB-Video) and metadata (source, importer, transforms applied).

Frame pixels are never held all at once: a scene reads them through a :class:`FrameSource`
(the importer's files, or memory-mapped arrays of a saved scene). Code after import never knows
where a capture came from.
"""

from __future__ import annotations

import datetime as _dt
import mmap
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol, Sequence

import numpy as np

from presim.capture.calibration import PhotometricCalib
from presim.geometry import Intrinsics, compose, transform_points

__all__ = [
    "Frame",
    "FrameSource",
    "ArrayFrameSource",
    "FloorPlane",
    "PointCloud",
    "SceneObject",
    "SceneMeta",
    "AppliedTransform",
    "Scene",
    "SceneError",
    "check_scene_geometry",
    "MAX_COORD_M",
    "MAX_EXTENT_M",
    "MIN_FOV_DEG",
    "release_frames",
]

MAX_COORD_M = 100_000.0
"""Largest camera coordinate a capture may have (±100 km): far beyond any room, building or site a
handheld capture covers, and far inside what float32 point clouds and voxel keys represent."""
MAX_EXTENT_M = 10_000.0
"""Largest extent of a capture's camera centres along any axis (10 km)."""
MIN_FOV_DEG = 0.01
"""Smallest field of view along either image axis (fx = 1e30 would give ~0 deg: no pixel sees
anything a neighbouring view could fill)."""


class SceneError(ValueError):
    """Bad input while reading or building a scene; the message names the file and the problem."""


def check_scene_geometry(T_world_cam: np.ndarray, intrinsics: Sequence[Intrinsics], frame_ids: Sequence[str],
                         where: str) -> None:
    """Refuse absurd geometry with one line naming ``where`` and the first frame at fault: a camera
    coordinate beyond ±:data:`MAX_COORD_M`, camera centres spread over more than
    :data:`MAX_EXTENT_M` along an axis, a field of view under :data:`MIN_FOV_DEG`, a focal length
    or principal point that is not a finite number."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    t = T[:, :3, 3]
    bad = ~np.all(np.isfinite(t) & (np.abs(t) <= MAX_COORD_M), axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise SceneError(f"{where}: frame {frame_ids[i]}: camera position {t[i].tolist()} m is beyond "
                         f"±{MAX_COORD_M / 1000:.0f} km (wrong unit or a corrupt pose?)")
    if len(t):
        ext = t.max(axis=0) - t.min(axis=0)
        if ext.max() > MAX_EXTENT_M:
            raise SceneError(f"{where}: the cameras spread over {ext.max() / 1000:.1f} km along "
                             f"{'xyz'[int(np.argmax(ext))]}, more than {MAX_EXTENT_M / 1000:.0f} km (wrong unit "
                             "or a corrupt pose?)")
    seen: set = set()
    for fid, K in zip(frame_ids, intrinsics):
        if K in seen:
            continue
        seen.add(K)
        vals = (K.fx, K.fy, K.cx, K.cy)
        if not all(isinstance(v, (int, float, np.floating, np.integer)) and np.isfinite(v) for v in vals) \
                or K.fx <= 0 or K.fy <= 0:
            raise SceneError(f"{where}: frame {fid}: intrinsics fx {K.fx!r} fy {K.fy!r} cx {K.cx!r} cy {K.cy!r} "
                             "must be finite, focal lengths > 0")
        if K.hfov_deg < MIN_FOV_DEG or K.vfov_deg < MIN_FOV_DEG:
            raise SceneError(f"{where}: frame {fid}: field of view {K.hfov_deg:.3g} x {K.vfov_deg:.3g} deg "
                             f"(fx {K.fx:.6g}, fy {K.fy:.6g} at {K.width}x{K.height}) is under {MIN_FOV_DEG} deg "
                             "(focal length in the wrong unit?)")


@dataclass(frozen=True)
class Frame:
    """One captured RGB-D frame."""

    frame_id: str
    """Identifier from the source (e.g. ``frame-000015``)."""
    stamp_s: float
    """Capture time, seconds."""
    color: np.ndarray
    """uint8 (H, W, 3) RGB."""
    depth_m: np.ndarray
    """float32 (H, W) z-depth in metres, 0 = invalid."""
    K: Intrinsics
    """Intrinsics of color and depth (depth is registered to the color camera at import)."""
    T_world_cam: np.ndarray
    """4x4 camera-to-world pose (OpenCV camera)."""


class FrameSource(Protocol):
    """Reads the pixels of frame ``idx`` (position in the scene's frame order)."""

    def __len__(self) -> int: ...

    def load(self, idx: int) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(color uint8 HxWx3, depth_m float32 HxW)``; raise SceneError naming the file."""
        ...


def release_frames(source: FrameSource) -> None:
    """Let ``source`` drop the resident pages of frames it has read (``source.release()`` where it
    has one; a no-op otherwise). Call it while streaming over many frames of a memory-mapped scene."""
    rel = getattr(source, "release", None)
    if rel is not None:
        rel()


class ArrayFrameSource:
    """Frames held in (possibly memory-mapped) arrays: color (N,H,W,3) uint8, depth (N,H,W) float32."""

    def __init__(self, color: np.ndarray, depth_m: np.ndarray):
        if color.ndim != 4 or color.shape[-1] != 3 or color.dtype != np.uint8:
            raise SceneError(f"color array must be uint8 (N,H,W,3), got {color.dtype} {color.shape}")
        if depth_m.shape != color.shape[:3] or depth_m.dtype != np.float32:
            raise SceneError(f"depth array must be float32 {color.shape[:3]}, got {depth_m.dtype} {depth_m.shape}")
        self.color = color
        self.depth_m = depth_m

    def __len__(self) -> int:
        return int(self.color.shape[0])

    def load(self, idx: int) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.color[idx]), np.asarray(self.depth_m[idx])

    def release(self) -> None:
        """Drop this process's resident pages of memory-mapped arrays (they stay in the OS page
        cache and map in again on the next read), so a pass over every frame does not keep all of
        them resident. Arrays in memory are left alone."""
        for a in (self.color, self.depth_m):
            m = getattr(a, "_mmap", None)  # np.memmap's mapping (None for in-memory arrays)
            if m is not None and hasattr(mmap, "MADV_DONTNEED"):
                m.madvise(mmap.MADV_DONTNEED)


class _SubsetFrameSource:
    def __init__(self, base: FrameSource, indices: Sequence[int]):
        self.base = base
        self.indices = list(indices)

    def __len__(self) -> int:
        return len(self.indices)

    def load(self, idx: int) -> tuple[np.ndarray, np.ndarray]:
        return self.base.load(self.indices[idx])

    def release(self) -> None:
        release_frames(self.base)


@dataclass(frozen=True)
class FloorPlane:
    """Plane ``normal . p + offset = 0`` in the world frame, normal pointing up (against gravity)."""

    normal: tuple[float, float, float]
    offset: float
    inlier_frac: float = 0.0
    """Fraction of the scene's points within the RANSAC threshold of the plane."""

    def height_of(self, p_world: np.ndarray) -> np.ndarray:
        """Signed height of points above the floor, metres."""
        return np.asarray(p_world) @ np.asarray(self.normal) + self.offset


@dataclass(frozen=True)
class PointCloud:
    """Colored points in the world frame."""

    xyz: np.ndarray
    """float32 (M, 3) metres."""
    rgb: np.ndarray
    """uint8 (M, 3)."""

    def __post_init__(self) -> None:
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3 or self.rgb.shape != self.xyz.shape:
            raise SceneError(f"point cloud needs xyz (M,3) and rgb (M,3), got {self.xyz.shape}, {self.rgb.shape}")

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def transformed(self, T_new_old: np.ndarray) -> "PointCloud":
        return PointCloud(transform_points(T_new_old, self.xyz).astype(np.float32), self.rgb)


@dataclass(frozen=True)
class SceneObject:
    """A rigid object placed in the scene (its model lives in its own object frame)."""

    obj_id: int
    """Dataset object id (BOP ``obj_id``)."""
    name: str
    T_world_obj: np.ndarray
    """4x4 object-to-world pose, metres."""
    model_path: str | None = None
    """Mesh (PLY/OBJ) or point file in the object frame, metres. Relative paths are relative to the
    saved scene's folder."""
    symmetric: bool = False
    """Whether ADD-S (not ADD) applies to this object."""
    symmetry_axis: tuple[float, float, float] | None = None
    """Axis (object frame, through the object origin) of a continuous rotational symmetry, when
    known; written to BOP ``models_info.json`` as ``symmetries_continuous``."""


@dataclass(frozen=True)
class AppliedTransform:
    """A change of world frame an importer made: ``p_new = T_new_old @ p_old``. Never rescales."""

    name: str
    T_new_old: np.ndarray

    def to_dict(self) -> dict:
        return {"name": self.name, "T_new_old": np.asarray(self.T_new_old).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "AppliedTransform":
        return cls(d["name"], np.asarray(d["T_new_old"], dtype=np.float64))


@dataclass(frozen=True)
class SceneMeta:
    """Where a scene came from and what was done to it."""

    source: str
    """Path of the imported capture (or a description, e.g. ``sample-scene seed=0``)."""
    source_format: str
    """Importer name, e.g. ``kinfu``, ``tum``, ``bop``, ``sample``."""
    importer_version: str = "1"
    transforms: tuple[AppliedTransform, ...] = ()
    created_utc: str = field(default_factory=lambda: _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    notes: tuple[str, ...] = ()
    """Free-text remarks (e.g. 'no floor found: tabletop capture')."""

    def to_dict(self) -> dict:
        return {
            "source": self.source,
            "source_format": self.source_format,
            "importer_version": self.importer_version,
            "transforms": [t.to_dict() for t in self.transforms],
            "created_utc": self.created_utc,
            "notes": list(self.notes),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "SceneMeta":
        return cls(
            source=d["source"], source_format=d["source_format"],
            importer_version=d.get("importer_version", "1"),
            transforms=tuple(AppliedTransform.from_dict(t) for t in d.get("transforms", [])),
            created_utc=d.get("created_utc", ""), notes=tuple(d.get("notes", [])),
        )


@dataclass
class Scene:
    """A captured scene. Build one with an importer (:mod:`presim.capture.importers`) or
    :func:`presim.capture.store.load_scene`; save with :func:`presim.capture.store.save_scene`.

    Example:
        >>> from presim.capture.store import load_scene
        >>> scene = load_scene("out/sample")          # doctest: +SKIP
        >>> f = scene.frame(0); f.color.shape, f.depth_m.dtype   # doctest: +SKIP
        ((480, 640, 3), dtype('float32'))
    """

    frame_ids: list[str]
    stamps_s: np.ndarray
    """(N,) float64 seconds."""
    T_world_cam: np.ndarray
    """(N, 4, 4) float64 camera-to-world."""
    intrinsics: list[Intrinsics]
    """Per-frame intrinsics (all frames share one resolution)."""
    frames: FrameSource
    meta: SceneMeta
    points: PointCloud | None = None
    floor: FloorPlane | None = None
    gravity_world: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    """Unit gravity direction in the world frame ((0,0,-1) once a floor was aligned)."""
    objects: list[SceneObject] = field(default_factory=list)
    depth_refined: np.ndarray | None = None
    """(N, H, W) float32 refined depth (``presim refine``), memory-mapped when loaded; None if absent."""
    depth_fused: np.ndarray | None = None
    """(N, H, W) float32 sensor depth aligned to and fused with the refined depth (``presim fuse``,
    thesis §5.3.4), memory-mapped when loaded; None if absent."""
    depth_completed: np.ndarray | None = None
    """(N, H, W) float32 depth completed where the depth the renderer uses has none (``presim complete``,
    :mod:`presim.depth.complete`; 0 elsewhere), memory-mapped when loaded; None if absent."""
    path: Path | None = None
    """Folder of the saved scene (None until saved/loaded)."""
    poses_source: str = "given"
    """Which camera poses ``T_world_cam`` holds: ``"given"`` (the capture's) or ``"refined"``
    (``presim align``'s, from ``SCENE/poses_refined.json``; see ``store.load_scene(poses=...)``);
    ``"none"`` only between an importer and ``import_capture`` for a capture without poses
    (placeholders, estimated there)."""
    photometric: "PhotometricCalib | None" = None
    """Per-frame colour transforms keyed by frame id (``presim photometric``,
    :mod:`presim.photometric`); None if absent. Subsets keep it (lookups are by id)."""
    render_filter_sigma_px: float | None = None
    """Sigma (pixels at the capture's sampling) of the renderer's reconstruction filter fitted on this
    capture (``presim fit-filter``, ``SCENE/render_filter.json``); None if absent."""

    def __post_init__(self) -> None:
        n = len(self.frame_ids)
        self.stamps_s = np.asarray(self.stamps_s, dtype=np.float64)
        self.T_world_cam = np.asarray(self.T_world_cam, dtype=np.float64)
        if self.stamps_s.shape != (n,):
            raise SceneError(f"{n} frame ids but stamps of shape {self.stamps_s.shape}")
        if self.T_world_cam.shape != (n, 4, 4):
            raise SceneError(f"{n} frame ids but poses of shape {self.T_world_cam.shape}")
        if len(self.intrinsics) != n or len(self.frames) != n:
            raise SceneError(f"{n} frame ids, {len(self.intrinsics)} intrinsics, {len(self.frames)} frames")
        if n == 0:
            raise SceneError("a scene needs at least one frame")
        sizes = {K.size_wh for K in self.intrinsics}
        if len(sizes) != 1:
            raise SceneError(f"all frames of a scene must share one resolution, got {sorted(sizes)}")
        if len(set(self.frame_ids)) != n:
            raise SceneError("frame ids must be unique")

    # ---- sizes ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def width(self) -> int:
        return self.intrinsics[0].width

    @property
    def height(self) -> int:
        return self.intrinsics[0].height

    # ---- pixels --------------------------------------------------------------------------------
    def frame(self, idx: int, refined: bool = False) -> Frame:
        """Frame at position ``idx``; with ``refined=True`` its refined depth when the scene has it."""
        color, depth = self.frames.load(idx)
        if refined and self.depth_refined is not None:
            depth = np.asarray(self.depth_refined[idx])
        return Frame(self.frame_ids[idx], float(self.stamps_s[idx]), color, depth,
                     self.intrinsics[idx], self.T_world_cam[idx])

    def depth(self, idx: int, refined: bool = True) -> np.ndarray:
        """Depth of frame ``idx`` in metres; refined when available and asked for."""
        if refined and self.depth_refined is not None:
            return np.asarray(self.depth_refined[idx])
        return self.frames.load(idx)[1]

    @property
    def has_refined_depth(self) -> bool:
        return self.depth_refined is not None

    @property
    def has_fused_depth(self) -> bool:
        return self.depth_fused is not None

    # ---- derived quantities --------------------------------------------------------------------
    @property
    def camera_centres(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame."""
        return self.T_world_cam[:, :3, 3].copy()

    def trajectory_length_m(self) -> float:
        c = self.camera_centres
        return float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum()) if len(c) > 1 else 0.0

    # ---- editing (returns new scenes; frames are shared, never copied) ------------------------
    def transformed(self, T_new_old: np.ndarray, name: str) -> "Scene":
        """The same scene in a new world frame ``p_new = T_new_old @ p_old`` (recorded in meta)."""
        T = np.asarray(T_new_old, dtype=np.float64)
        R = T[:3, :3]
        if abs(np.linalg.det(R) - 1.0) > 1e-6:
            raise SceneError("a world-frame change must be a rotation + translation (no scale)")
        floor = None
        if self.floor is not None:
            n_new = R @ np.asarray(self.floor.normal)
            # n.p_old + d = 0, p_old = R^T (p_new - t)  =>  (R n).p_new + d - (R n).t = 0
            floor = FloorPlane(tuple(n_new), float(self.floor.offset - n_new @ T[:3, 3]), self.floor.inlier_frac)
        return replace(
            self,
            T_world_cam=compose(T, self.T_world_cam),
            points=self.points.transformed(T) if self.points is not None else None,
            floor=floor,
            gravity_world=R @ self.gravity_world,
            objects=[replace(o, T_world_obj=compose(T, o.T_world_obj)) for o in self.objects],
            meta=replace(self.meta, transforms=self.meta.transforms + (AppliedTransform(name, T),)),
            path=None,
        )

    def subset(self, indices: Sequence[int]) -> "Scene":
        """A scene of the frames at ``indices`` (in that order)."""
        idx = [int(i) for i in indices]
        if not idx:
            raise SceneError("subset needs at least one frame")
        return replace(
            self,
            frame_ids=[self.frame_ids[i] for i in idx],
            stamps_s=self.stamps_s[idx],
            T_world_cam=self.T_world_cam[idx],
            intrinsics=[self.intrinsics[i] for i in idx],
            frames=_SubsetFrameSource(self.frames, idx),
            depth_refined=None if self.depth_refined is None else _LazyRows(self.depth_refined, idx),
            depth_fused=None if self.depth_fused is None else _LazyRows(self.depth_fused, idx),
            depth_completed=None if self.depth_completed is None else _LazyRows(self.depth_completed, idx),
            path=None,
        )


class _LazyRows:
    """Row view ``base[indices[i]]`` that never copies the whole base array."""

    def __init__(self, base, indices: Sequence[int]):
        self.base, self.indices = base, list(indices)
        self.shape = (len(self.indices),) + tuple(base.shape[1:])
        self.dtype = base.dtype

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> np.ndarray:
        return np.asarray(self.base[self.indices[i]])
