"""Axis-aligned box models with known geometry, for pose tests (metres, centred at the origin)."""

from __future__ import annotations

import numpy as np

__all__ = ["box_mesh", "box_surface_points"]


def box_mesh(size) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (8, 3) float64, triangles (12, 3))`` of a box of side lengths ``size``, outward faces."""
    h = np.asarray(size) / 2
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * h
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def box_surface_points(size, n: int = 9) -> np.ndarray:
    """Points of an ``n``-per-axis grid that lie on the surface of a box of side lengths ``size``."""
    g = np.linspace(-0.5, 0.5, n)
    return np.array([[x, y, z] for x in g for y in g for z in g if max(abs(x), abs(y), abs(z)) == 0.5]) * size
