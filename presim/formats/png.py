"""PNG bytes of an in-memory image (RGB order in memory, OpenCV's BGR only inside this border)."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["encode_png"]


def encode_png(image: np.ndarray, compression: int | None = None) -> bytes:
    """PNG bytes of an RGB uint8 (H, W, 3), gray uint8 / uint16 (H, W) or boolean (H, W) image.

    Booleans are stored as 0 / 255. ``compression`` is OpenCV's PNG level 0-9; None = OpenCV's
    default (the bytes ``presim.io_utils.write_png`` writes).

    Example:
        >>> encode_png(np.zeros((2, 3), np.uint16))[:4]
        b'\\x89PNG'
    """
    img = np.asarray(image)
    if img.ndim == 3:
        if img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"color PNGs must be uint8 HxWx3, got {img.dtype} {img.shape}")
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR)  # RGB in memory, BGR for OpenCV
    elif img.ndim != 2 or img.dtype not in (np.uint8, np.uint16, np.bool_):
        raise ValueError(f"single-channel PNGs must be uint8/uint16/bool HxW, got {img.dtype} {img.shape}")
    if img.dtype == np.bool_:
        img = img.astype(np.uint8) * 255
    params = [] if compression is None else [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]
    ok, buf = cv2.imencode(".png", img, params)
    if not ok:
        raise OSError("PNG encoding failed")
    return buf.tobytes()
