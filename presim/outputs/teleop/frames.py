"""What the teleop page shows, computed from simulator output: a depth colour map with a fixed metre
range, JPEG bytes, the hole fraction and the top-down map. Pure functions of arrays."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["MapImage", "colorize_depth", "depth_colorbar", "encode_jpeg", "encode_png", "hole_fraction",
           "top_down_map", "depth_range_m"]


def colorize_depth(depth_m: np.ndarray, max_m: float) -> np.ndarray:
    """uint8 (H, W, 3) RGB: 0 m (near) .. ``max_m`` (far) on the turbo colour map; invalid (0) black."""
    if not max_m > 0:
        raise ValueError(f"depth colour range must be > 0 m, got {max_m}")
    d = np.asarray(depth_m, dtype=np.float32)
    idx = np.clip(d * (255.0 / max_m), 0, 255).astype(np.uint8)
    bgr = cv2.applyColorMap(idx, cv2.COLORMAP_TURBO)
    bgr[~(d > 0)] = 0
    return bgr[..., ::-1]


def depth_colorbar(width: int = 256, height: int = 12) -> np.ndarray:
    """uint8 (height, width, 3) RGB: the colour map from 0 (left) to the range's far end (right)."""
    row = np.linspace(0, 255, width).astype(np.uint8)[None, :]
    bgr = cv2.applyColorMap(np.repeat(row, height, axis=0), cv2.COLORMAP_TURBO)
    return bgr[..., ::-1]


def depth_range_m(depth_m: np.ndarray, percentile: float = 98.0, step_m: float = 0.5) -> float:
    """Colour-bar range for a scene: the ``percentile`` of valid depth rounded up to ``step_m``
    (at least ``step_m``), so one fixed range serves the whole session."""
    d = np.asarray(depth_m)[np.asarray(depth_m) > 0]
    if d.size == 0:
        return 5.0
    return float(max(step_m, np.ceil(np.percentile(d, percentile) / step_m) * step_m))


def encode_jpeg(rgb: np.ndarray, quality: int = 80) -> bytes:
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def encode_png(img: np.ndarray) -> bytes:
    """PNG bytes of an RGB uint8 image or a single-channel (uint8 / uint16) image."""
    a = np.ascontiguousarray(img[..., ::-1] if img.ndim == 3 else img)
    ok, buf = cv2.imencode(".png", a)
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def hole_fraction(valid: np.ndarray, depth_m: np.ndarray) -> float:
    """Fraction of pixels not synthesized from captured views (filled) or without depth."""
    bad = ~np.asarray(valid, dtype=bool) | ~(np.asarray(depth_m) > 0)
    return float(bad.mean()) if bad.size else 0.0


@dataclass(frozen=True)
class MapImage:
    """Top-down map. Pixel (row r, col c) covers world ``x in [ox + c*res, ox + (c+1)*res)`` and
    ``y in [oy + (H-1-r)*res, oy + (H-r)*res)`` (north = +y is up on the page)."""

    rgb: np.ndarray
    """uint8 (H, W, 3)."""
    origin_xy: tuple[float, float]
    """World (x, y) of the map's lower-left corner, metres."""
    resolution_m: float

    @property
    def max_xy(self) -> tuple[float, float]:
        h, w = self.rgb.shape[:2]
        return (self.origin_xy[0] + w * self.resolution_m, self.origin_xy[1] + h * self.resolution_m)


def top_down_map(points_xyz: np.ndarray, points_rgb: np.ndarray, *, occupied: np.ndarray | None = None,
                 known: np.ndarray | None = None, origin_xy: tuple[float, float] | None = None,
                 resolution_m: float = 0.05, z_max_m: float | None = None, pad_m: float = 0.5,
                 footprint: bool = False) -> MapImage:
    """Map from the scene points (mean colour per cell of the points below ``z_max_m``), with the
    occupancy grid (``occupied`` / ``known``, rows = +y, its ``origin_xy``) drawn over it when given:
    occupied cells tinted red, unknown cells grey. Without a grid the map covers the points plus
    ``pad_m``; ``footprint`` then outlines the points' footprint (cells with points, closed over 5x5
    cells; its border cells) in cyan and darkens the empty cells, so a capture without a floor still shows
    where its data lies."""
    xyz = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray(points_rgb, dtype=np.float64).reshape(-1, 3)
    if z_max_m is not None:
        keep = xyz[:, 2] <= z_max_m
        xyz, rgb = xyz[keep], rgb[keep]
    if occupied is not None:
        h, w = occupied.shape
        ox, oy = float(origin_xy[0]), float(origin_xy[1])
    else:
        if len(xyz) == 0:
            raise ValueError("top-down map: no scene points and no occupancy grid")
        lo, hi = xyz[:, :2].min(0) - pad_m, xyz[:, :2].max(0) + pad_m
        ox, oy = float(lo[0]), float(lo[1])
        w, h = (int(np.ceil((hi - lo)[k] / resolution_m)) for k in (0, 1))
    j = np.floor((xyz[:, 0] - ox) / resolution_m).astype(np.int64)
    i = np.floor((xyz[:, 1] - oy) / resolution_m).astype(np.int64)
    ok = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    flat = i[ok] * w + j[ok]
    count = np.bincount(flat, minlength=h * w).astype(np.float64)
    img = np.empty((h * w, 3))
    for c in range(3):
        s = np.bincount(flat, weights=rgb[ok, c], minlength=h * w)
        img[:, c] = np.where(count > 0, s / np.maximum(count, 1), 70.0)
    img = img.reshape(h, w, 3)
    if footprint and occupied is None:
        # closed over 5x5 cells first, so the outline follows the cloud, not its sampling gaps
        k5, k3, edge = np.ones((5, 5), np.uint8), np.ones((3, 3), np.uint8), dict(borderType=cv2.BORDER_CONSTANT,
                                                                                 borderValue=0)
        has = cv2.erode(cv2.dilate((count.reshape(h, w) > 0).astype(np.uint8), k5, **edge), k5, **edge)
        inner = cv2.erode(has, k3, **edge)
        has, inner = has.astype(bool), inner.astype(bool)
        img[~has] = 35.0
        img[has & ~inner] = (0.0, 210.0, 230.0)
    if occupied is not None:
        if known is not None:
            img[~known & (count.reshape(h, w) == 0)] = 70.0
        img[occupied] = 0.45 * img[occupied] + 0.55 * np.array([200.0, 30.0, 30.0])
    return MapImage(np.ascontiguousarray(np.clip(img, 0, 255).astype(np.uint8)[::-1]), (ox, oy), float(resolution_m))
