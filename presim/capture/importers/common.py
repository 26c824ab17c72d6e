"""Pieces every importer shares: the lazy file-backed frame source, depth decoders, text readers.

Importers never load pixels at import time: they list files, read poses / intrinsics / stamps (small
text) and hand a :class:`FileFrameSource` to the :class:`~presim.capture.scene.Scene`; pixels are read
one frame at a time when a consumer (``save_scene``, the point-cloud fusion) asks for them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from presim.capture.register_depth import register_depth
from presim.capture.scene import SceneError
from presim.geometry import Intrinsics, check_rigid
from presim.io_utils import read_image

__all__ = [
    "DepthDecoder", "DepthCamera", "Undistortion", "FileFrameSource", "select_indices",
    "read_matrix_txt", "checked_pose", "decode_depth_png_scale", "image_size_wh", "require_file",
    "override_depth_scale",
]

DepthDecoder = Callable[[np.ndarray, Path], np.ndarray]
"""(raw image as stored, path) -> float32 depth in metres, 0 = invalid."""


def decode_depth_png_scale(scale_m_per_unit: float, invalid_codes: Sequence[int] = (0,)) -> DepthDecoder:
    """Decoder for integer depth PNGs: ``depth_m = value * scale_m_per_unit``; ``invalid_codes`` -> 0."""

    def decode(raw: np.ndarray, path: Path) -> np.ndarray:
        if not np.issubdtype(raw.dtype, np.integer):
            raise SceneError(f"{path}: depth PNG must be integer (uint16), got {raw.dtype}")
        depth = raw.astype(np.float32) * np.float32(scale_m_per_unit)
        for code in invalid_codes:
            depth[raw == code] = 0.0
        return depth

    return decode


def override_depth_scale(source, depth_scale_mm: float, where: str) -> None:
    """Decode ``source``'s depth images as ``depth_mm = value * depth_scale_mm`` (``presim import
    --depth-scale``), 8-bit ones included; 0 stays invalid."""
    if not isinstance(source, FileFrameSource):
        raise SceneError(f"{where}: --depth-scale applies to captures with integer depth images; this "
                         "capture's depth is not read from images")
    if not (np.isfinite(depth_scale_mm) and depth_scale_mm > 0):
        raise SceneError(f"--depth-scale: must be a positive finite number of millimetres, got {depth_scale_mm!r}")
    source.decode_depth = decode_depth_png_scale(depth_scale_mm * 1e-3)
    source.depth_unit_given = True


def sanitize_depth(depth: np.ndarray, path: Path) -> np.ndarray:
    """Float depth from a file: NaN / inf / negative -> 0 (the in-memory convention), float32."""
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise SceneError(f"{path}: depth must be a 2-D array, got shape {d.shape}")
    bad = ~np.isfinite(d) | (d < 0)
    if bad.any():
        d = d.copy()
        d[bad] = 0.0
    return d


@dataclass(frozen=True)
class DepthCamera:
    """A depth sensor that is not the color camera: its intrinsics and ``T_color_depth``."""

    K: Intrinsics
    """Intrinsics of the raw depth image."""
    T_color_depth: np.ndarray
    """4x4 depth-camera -> color-camera transform, metres."""


@dataclass(frozen=True)
class Undistortion:
    """OpenCV distortion of the raw images; frames are undistorted to ``K_out`` when read."""

    K_raw: Intrinsics
    dist_coeffs: tuple[float, ...]
    """OpenCV order k1, k2, p1, p2[, k3...]."""
    K_out: Intrinsics

    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        return cv2.initUndistortRectifyMap(self.K_raw.K, np.asarray(self.dist_coeffs, np.float64), None,
                                           self.K_out.K, self.K_out.size_wh, cv2.CV_32FC1)


class FileFrameSource:
    """Lazy frame source over color / depth image files (one frame read per :meth:`load`).

    Args:
        color_paths, depth_paths: one per frame.
        K: intrinsics of the (undistorted, registered) color frame; every image is checked against it.
        decode_depth: raw depth array (as read) -> float32 metres.
        depth_camera: when set, depth files are in this camera and are registered into the color
            camera on load (:func:`presim.capture.register_depth.register_depth`).
        undistortion: when set, color and depth are undistorted (depth with nearest interpolation).
        require_depth: raise when a depth map has no valid pixel.
        depth_unit_given: the user said what one step of the depth images is (``--depth-scale``);
            without it an 8-bit depth image is refused (its 256 steps have no standard unit).
    """

    def __init__(self, color_paths: Sequence[Path], depth_paths: Sequence[Path],
                 K: Intrinsics | Sequence[Intrinsics], decode_depth: DepthDecoder,
                 depth_camera: DepthCamera | None = None,
                 undistortion: Undistortion | Sequence[Undistortion | None] | None = None,
                 require_depth: bool = True, depth_unit_given: bool = False):
        n = len(color_paths)
        if len(depth_paths) != n:
            raise SceneError(f"{n} color files but {len(depth_paths)} depth files")
        self.color_paths = [Path(p) for p in color_paths]
        self.depth_paths = [Path(p) for p in depth_paths]
        self.Ks = [K] * n if isinstance(K, Intrinsics) else list(K)
        self.decode_depth = decode_depth
        self.depth_camera = depth_camera
        self.undistortions = (list(undistortion) if isinstance(undistortion, (list, tuple))
                              else [undistortion] * n)
        if len(self.Ks) != n or len(self.undistortions) != n:
            raise SceneError(f"{n} frames but {len(self.Ks)} intrinsics / {len(self.undistortions)} distortions")
        self.require_depth = require_depth
        self.depth_unit_given = depth_unit_given
        self._maps: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    @property
    def K(self) -> Intrinsics:
        return self.Ks[0]

    def __len__(self) -> int:
        return len(self.color_paths)

    def _read(self, path: Path, kind: str) -> np.ndarray:
        try:
            if kind == "depth" and path.suffix.lower() == ".npy":
                try:
                    return np.load(path, allow_pickle=False)
                except FileNotFoundError:
                    raise
                except Exception as e:  # noqa: BLE001 - any numpy parse error = corrupt file
                    raise SceneError(f"{path}: unreadable or corrupt .npy depth ({e})") from e
            return read_image(path, kind=kind)
        except FileNotFoundError as e:
            raise SceneError(f"{path}: file not found") from e
        except SceneError:
            raise
        except ValueError as e:
            raise SceneError(str(e)) from e

    def load(self, idx: int) -> tuple[np.ndarray, np.ndarray]:
        cpath, dpath = self.color_paths[idx], self.depth_paths[idx]
        color = self._read(cpath, "color")
        raw = self._read(dpath, "depth")
        if raw.ndim == 3 and raw.shape[-1] == 1:
            raw = raw[..., 0]
        if raw.dtype == np.uint8 and not self.depth_unit_given:
            raise SceneError(f"{dpath}: 8-bit depth image: its unit is unknown (depth images are 16-bit); "
                             "pass --depth-scale MM (millimetres per step, e.g. 10 for centimetres) if it "
                             "really is depth")
        depth = sanitize_depth(self.decode_depth(raw, dpath), dpath)
        K = self.Ks[idx]
        u = self.undistortions[idx]
        if u is not None:
            exp = (u.K_raw.height, u.K_raw.width)
            # A separate depth camera's images are not undistorted (its distortion is not modelled).
            pairs = ((cpath, color),) if self.depth_camera is not None else ((cpath, color), (dpath, depth))
            for p, a in pairs:
                if a.shape[:2] != exp:
                    raise SceneError(f"{p}: resolution {a.shape[1]}x{a.shape[0]} != camera {exp[1]}x{exp[0]}")
            if id(u) not in self._maps:
                self._maps[id(u)] = u.maps()
            m1, m2 = self._maps[id(u)]
            color = cv2.remap(color, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            if self.depth_camera is None:
                # Nearest for depth: interpolating across a depth edge invents surfaces in mid-air.
                depth = cv2.remap(depth, m1, m2, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        if color.shape != (K.height, K.width, 3):
            raise SceneError(f"{cpath}: resolution {color.shape[1]}x{color.shape[0]} != intrinsics "
                             f"{K.width}x{K.height}")
        if self.depth_camera is not None:
            Kd = self.depth_camera.K
            if depth.shape != (Kd.height, Kd.width):
                raise SceneError(f"{dpath}: resolution {depth.shape[1]}x{depth.shape[0]} != depth camera "
                                 f"{Kd.width}x{Kd.height}")
            depth = register_depth(depth, Kd, K, self.depth_camera.T_color_depth)
        elif depth.shape != (K.height, K.width):
            raise SceneError(f"{dpath}: resolution {depth.shape[1]}x{depth.shape[0]} != color "
                             f"{K.width}x{K.height} (pass a separate depth camera if it is not registered)")
        if self.require_depth and not (depth > 0).any():
            raise SceneError(f"{dpath}: empty depth (no valid pixel)")
        return np.ascontiguousarray(color, dtype=np.uint8), np.ascontiguousarray(depth, dtype=np.float32)


def select_indices(n: int, every: int = 1, max_frames: int | None = None) -> list[int]:
    """Positions kept by ``--every N --max-frames M``: 0, N, 2N, ... (at most M)."""
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    idx = list(range(0, n, every))
    return idx[:max_frames] if max_frames is not None else idx


def require_file(path: Path, what: str = "file") -> Path:
    if not path.is_file():
        raise SceneError(f"{path}: {what} not found")
    return path


def read_matrix_txt(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """Whitespace-separated numbers of a text file (``#`` comments allowed) as a ``shape`` matrix."""
    require_file(path)
    try:
        vals = np.loadtxt(path, comments="#", dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise SceneError(f"{path}: not a matrix of numbers ({e})") from e
    if vals.size != shape[0] * shape[1]:
        raise SceneError(f"{path}: expected a {shape[0]}x{shape[1]} matrix, got {vals.size} numbers")
    return vals.reshape(shape)


def checked_pose(T: np.ndarray, where: str) -> np.ndarray:
    """Validate a 4x4 pose (finite, rigid) with an error naming ``where`` (file / frame)."""
    try:
        return check_rigid(np.asarray(T, dtype=np.float64), what=where)
    except ValueError as e:
        raise SceneError(str(e)) from e


def image_size_wh(path: Path) -> tuple[int, int]:
    """Width and height from an image header, without decoding the pixels."""
    from PIL import Image

    require_file(path)
    try:
        with Image.open(path) as im:
            return im.size
    except Exception as e:  # noqa: BLE001 - any PIL failure means unreadable/corrupt
        raise SceneError(f"{path}: unreadable or corrupt image ({e})") from e


def check_sizes(paths: Sequence[Path], size_wh: tuple[int, int], what: str) -> None:
    """Check each image's header resolution (cheap) so a mismatch fails at import, naming the file."""
    for p in paths:
        wh = image_size_wh(p)
        if wh != tuple(size_wh):
            raise SceneError(f"{p}: {what} resolution {wh[0]}x{wh[1]} != expected {size_wh[0]}x{size_wh[1]}")


def frame_id_of(path: Path, suffix: str) -> str:
    name = path.name
    return name[: -len(suffix)] if name.endswith(suffix) else path.stem


DEPTH_INTRINSICS_FILE = "depth-intrinsics.txt"
DEPTH_EXTRINSIC_FILE = "depth-to-color.txt"


def read_depth_camera(folder: Path, first_depth: Path) -> DepthCamera | None:
    """A separate (unregistered) depth camera of a folder capture, when the folder has
    ``depth-intrinsics.txt`` (3x3 K of the depth images) and ``depth-to-color.txt`` (4x4
    ``T_color_depth``, metres). Any folder format (kinfu, TUM, COLMAP, nerfstudio) accepts them; the
    depth is then registered into the color camera frame by frame when read."""
    ki, ke = folder / DEPTH_INTRINSICS_FILE, folder / DEPTH_EXTRINSIC_FILE
    if not ki.is_file() and not ke.is_file():
        return None
    if not (ki.is_file() and ke.is_file()):
        missing = ke if ki.is_file() else ki
        raise SceneError(f"{missing}: not found (a separate depth camera needs both {DEPTH_INTRINSICS_FILE} "
                         f"and {DEPTH_EXTRINSIC_FILE})")
    K = read_matrix_txt(ki, (3, 3))
    if first_depth.suffix.lower() == ".npy":
        shape = np.load(first_depth, mmap_mode="r").shape
        wh = (shape[1], shape[0])
    else:
        wh = image_size_wh(first_depth)
    T = checked_pose(read_matrix_txt(ke, (4, 4)), str(ke))
    try:
        return DepthCamera(Intrinsics.from_K(K, *wh), T)
    except ValueError as e:
        raise SceneError(f"{ki}: {e}") from None
