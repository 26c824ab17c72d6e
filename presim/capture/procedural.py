"""Procedural geometry and textures for the built-in sample scene.

Everything here is a pure function of its inputs (and of a seed), vectorised with numpy:

- meshes: :class:`Mesh` (vertices, triangles, per-vertex normals) and builders for boxes, cylinders,
  ellipsoids, noisy "rocks" and unions of boxes. Flat faces get their own (unshared) vertices so
  per-vertex normals are exact face normals; curved surfaces share vertices for smooth shading.
- textures: :func:`albedo` evaluates a :class:`Material` at points given in the part's own frame.
  Patterns are band-limited (smooth edges a few millimetres wide, noise octaves no finer than
  ``Material.scale_m / 8``) so that point-sampled renderings of the same surface seen from two
  cameras agree after reprojection (no aliasing flicker).

Textures are *solid* (functions of 3D position) or use a planar projection picked by the dominant
axis of the local normal; no UV atlas is needed and nothing depends on the viewing direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np


__all__ = [
    "Mesh", "box_mesh", "cylinder_mesh", "ellipsoid_mesh", "rock_mesh", "merge_meshes",
    "Material", "NoiseField", "albedo", "srgb_encode",
]


# ---- meshes -------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Mesh:
    """Triangle mesh with per-vertex normals (outward, unit)."""

    vertices: np.ndarray
    """float64 (V, 3) metres."""
    triangles: np.ndarray
    """int64 (T, 3) vertex indices, counter-clockwise seen from outside."""
    normals: np.ndarray
    """float64 (V, 3) unit vertex normals."""

    def transformed(self, T: np.ndarray) -> "Mesh":
        R, t = T[:3, :3], T[:3, 3]
        return Mesh(self.vertices @ R.T + t, self.triangles, self.normals @ R.T)

    def flipped(self) -> "Mesh":
        """Inward-facing copy (normals and winding reversed)."""
        return Mesh(self.vertices, self.triangles[:, ::-1].copy(), -self.normals)


def merge_meshes(meshes: list[Mesh]) -> Mesh:
    verts, tris, norms, off = [], [], [], 0
    for m in meshes:
        verts.append(m.vertices)
        tris.append(m.triangles + off)
        norms.append(m.normals)
        off += len(m.vertices)
    return Mesh(np.concatenate(verts), np.concatenate(tris), np.concatenate(norms))


def box_mesh(lo, hi) -> Mesh:
    """Axis-aligned closed box from corner ``lo`` to ``hi`` (metres), 12 triangles, outward normals."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    verts, tris, norms = [], [], []
    for axis in range(3):
        for side in (0, 1):
            n = np.zeros(3)
            n[axis] = 1.0 if side else -1.0
            a, b = (axis + 1) % 3, (axis + 2) % 3
            c = np.where(np.arange(3) == axis, hi if side else lo, 0.0)
            quad = []
            for ua, ub in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = c.copy()
                p[a] = hi[a] if ua else lo[a]
                p[b] = hi[b] if ub else lo[b]
                quad.append(p)
            quad = np.array(quad)
            base = len(verts) * 4
            t = np.array([[0, 1, 2], [0, 2, 3]]) + base
            # a x b = axis direction for the cyclic order; flip winding on the negative side.
            if not side:
                t = t[:, ::-1]
            verts.append(quad)
            tris.append(t)
            norms.append(np.tile(n, (4, 1)))
    return Mesh(np.concatenate(verts), np.concatenate(tris), np.concatenate(norms))


def cylinder_mesh(radius_m: float, height_m: float, segments: int = 48) -> Mesh:
    """Closed upright cylinder, axis +z, bottom centre at the origin; smooth side, flat caps."""
    ang = np.arange(segments) * (2 * np.pi / segments)
    c, s = np.cos(ang), np.sin(ang)
    ring0 = np.stack([radius_m * c, radius_m * s, np.zeros(segments)], 1)
    ring1 = ring0 + [0, 0, height_m]
    side_n = np.stack([c, s, np.zeros(segments)], 1)
    i = np.arange(segments)
    j = (i + 1) % segments
    side_t = np.concatenate([np.stack([i, j, segments + j], 1), np.stack([i, segments + j, segments + i], 1)])
    side = Mesh(np.concatenate([ring0, ring1]), side_t, np.concatenate([side_n, side_n]))
    # caps: centre vertex + ring, own vertices for flat normals
    top_v = np.concatenate([[[0, 0, height_m]], ring1])
    top_t = np.stack([np.zeros(segments, int), 1 + i, 1 + j], 1)
    top = Mesh(top_v, top_t, np.tile([0.0, 0.0, 1.0], (segments + 1, 1)))
    bot_v = np.concatenate([[[0, 0, 0.0]], ring0])
    bot = Mesh(bot_v, top_t[:, ::-1].copy(), np.tile([0.0, 0.0, -1.0], (segments + 1, 1)))
    return merge_meshes([side, top, bot])


def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    t = (1.0 + 5 ** 0.5) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
                  [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)  # midpoints of edges (01, 12, 20) per face
        v = np.concatenate([v, mid])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        m01, m12, m20 = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate([np.stack([a, m01, m20], 1), np.stack([b, m12, m01], 1),
                            np.stack([c, m20, m12], 1), np.stack([m01, m12, m20], 1)])
    return v, f


def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # area-weighted
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def ellipsoid_mesh(radii_m, subdivisions: int = 3) -> Mesh:
    """Smooth ellipsoid with semi-axes ``radii_m`` resting on z = 0 (lowest point at the origin)."""
    r = np.asarray(radii_m, dtype=np.float64)
    v, f = _icosphere(subdivisions)
    v = v * r + [0.0, 0.0, r[2]]
    return Mesh(v, f, _vertex_normals(v, f))


def rock_mesh(radius_m: float, rng: np.random.Generator, subdivisions: int = 3,
              bumpiness: float = 0.3, squash: float = 0.75) -> Mesh:
    """Irregular, non-convex blob: a sphere with smooth random radial bumps, lowest point on z = 0."""
    v, f = _icosphere(subdivisions)
    # Sum of a few random low-order "lobes" gives smooth dents and bumps (non-convex).
    disp = np.zeros(len(v))
    for _ in range(6):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        disp += rng.uniform(-1, 1) * np.exp(4.0 * (v @ d - 1.0))
    disp = disp / np.abs(disp).max()
    v = v * (radius_m * (1.0 + bumpiness * disp))[:, None]
    v[:, 2] *= squash
    v[:, 2] -= v[:, 2].min()
    return Mesh(v, f, _vertex_normals(v, f))


# ---- noise --------------------------------------------------------------------------------------

class NoiseField:
    """Periodic 3D value noise (a seeded 32^3 lattice, smoothstep-trilinear interpolation).

    ``fbm(p, scale_m)`` returns values in about [0, 1] whose finest octave has wavelength
    ``scale_m / 2**(octaves-1)``.
    """

    G = 32  # a power of two (the fast path wraps with a bit mask)

    def __init__(self, seed: int):
        self.lattice = np.random.default_rng([seed, 7919]).random((self.G,) * 3).astype(np.float32)

    def value(self, p: np.ndarray) -> np.ndarray:
        """Noise at lattice coordinates ``p`` (M, 3) -> (M,) in [0, 1]."""
        p = np.asarray(p, dtype=np.float64)
        i0 = np.floor(p)
        fr = p - i0
        w = fr * fr * (3.0 - 2.0 * fr)
        i0 = i0.astype(np.int64) % self.G
        i1 = (i0 + 1) % self.G
        L = self.lattice
        out = np.zeros(len(p))
        for cx in (0, 1):
            ix = i1[:, 0] if cx else i0[:, 0]
            wx = w[:, 0] if cx else 1.0 - w[:, 0]
            for cy in (0, 1):
                iy = i1[:, 1] if cy else i0[:, 1]
                wy = w[:, 1] if cy else 1.0 - w[:, 1]
                for cz in (0, 1):
                    iz = i1[:, 2] if cz else i0[:, 2]
                    wz = w[:, 2] if cz else 1.0 - w[:, 2]
                    out += wx * wy * wz * L[ix, iy, iz]
        return out

    def fbm(self, p: np.ndarray, scale_m: float, octaves: int = 4, salt: float = 0.0,
            backend: str = "numba") -> np.ndarray:
        """Fractal sum of ``octaves`` noise octaves at points ``p`` (M, 3) metres -> (M,) in ~[0, 1].

        ``backend``: ``"numba"`` (fast, parallel) or ``"reference"`` (numpy); they agree to 1e-12.
        """
        p = np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 3)
        if backend == "numba":
            return _fbm_numba(p, self.lattice, float(scale_m), int(octaves), float(salt))
        if backend != "reference":
            raise ValueError(f"unknown noise backend {backend!r} (numba | reference)")
        q = p * (1.0 / scale_m)
        total, amp, norm = np.zeros(len(q)), 1.0, 0.0
        for k in range(octaves):
            # Offsets between octaves hide the lattice alignment.
            off = np.array([13.7, 5.3, 29.1]) * (k + 1) + salt
            total += amp * self.value(q * (2.0 ** k) + off)
            norm += amp
            amp *= 0.5
        return total / norm


@numba.njit(inline="always")
def _lattice_coord(x, mask):
    fl = np.floor(x)
    fr = x - fl
    # Bitwise and == floor modulo for a power-of-two lattice (also for negative cells).
    return np.int64(fl) & mask, fr * fr * (3.0 - 2.0 * fr)


@numba.njit(parallel=True, cache=True)
def _fbm_numba(p, lattice, scale_m, octaves, salt):
    mask = lattice.shape[0] - 1
    inv_scale = 1.0 / scale_m
    out = np.empty(p.shape[0])
    for m in numba.prange(p.shape[0]):
        total = 0.0
        amp = 1.0
        norm = 0.0
        f = 1.0
        for k in range(octaves):
            ix, wx = _lattice_coord(p[m, 0] * inv_scale * f + (13.7 * (k + 1) + salt), mask)
            iy, wy = _lattice_coord(p[m, 1] * inv_scale * f + (5.3 * (k + 1) + salt), mask)
            iz, wz = _lattice_coord(p[m, 2] * inv_scale * f + (29.1 * (k + 1) + salt), mask)
            jx, jy, jz = (ix + 1) & mask, (iy + 1) & mask, (iz + 1) & mask
            c00 = lattice[ix, iy, iz] * (1.0 - wz) + lattice[ix, iy, jz] * wz
            c01 = lattice[ix, jy, iz] * (1.0 - wz) + lattice[ix, jy, jz] * wz
            c10 = lattice[jx, iy, iz] * (1.0 - wz) + lattice[jx, iy, jz] * wz
            c11 = lattice[jx, jy, iz] * (1.0 - wz) + lattice[jx, jy, jz] * wz
            v = (c00 * (1.0 - wy) + c01 * wy) * (1.0 - wx) + (c10 * (1.0 - wy) + c11 * wy) * wx
            total += amp * v
            norm += amp
            amp *= 0.5
            f *= 2.0
        out[m] = total / norm
    return out


# ---- materials ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Material:
    """A procedural, Lambertian material (albedo in linear RGB, 0..1)."""

    kind: str
    """Pattern: plaster, planks, wood, brick, wallpaper, checker, cardboard, painted, label, bands,
    beachball, stone, poster, books, dark."""
    color_a: tuple[float, float, float]
    """Main albedo (linear RGB)."""
    color_b: tuple[float, float, float] = (0.5, 0.5, 0.5)
    """Second albedo of two-color patterns (mortar, checker squares, grain, ...)."""
    scale_m: float = 0.2
    """Characteristic size of the pattern (plank width, brick length, checker square, noise scale)."""
    salt: float = 0.0
    """Per-material offset into the noise field (decorrelates materials of the same kind)."""


def _smooth_edge(x: np.ndarray, width: float) -> np.ndarray:
    """0 -> 1 ramp of ``width`` around x = 0 (anti-aliased pattern edges)."""
    t = np.clip(x / width + 0.5, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _hash01(*ints: np.ndarray) -> np.ndarray:
    """Deterministic per-cell random numbers in [0, 1) from integer cell indices."""
    h = np.uint64(1469598103934665603)
    out = np.full(np.broadcast(*ints).shape, h, dtype=np.uint64)
    for k, a in enumerate(ints):
        a = np.asarray(a).astype(np.int64).astype(np.uint64)
        out ^= a * np.uint64(0x9E3779B97F4A7C15 + 2 * k + 1)
        out *= np.uint64(1099511628211)
        out ^= out >> np.uint64(29)
    return (out >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def _planar_coords(p: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """2D coordinates on the plane most facing the normal: (x, y) on floors, (along, z) on walls."""
    ax = np.argmax(np.abs(n), axis=1)
    a = np.where(ax == 0, p[:, 1], p[:, 0])
    b = np.where(ax == 2, p[:, 1], p[:, 2])
    return a, b


def _mix(c0, c1, t: np.ndarray) -> np.ndarray:
    c0 = np.asarray(c0, dtype=np.float64)
    c1 = np.asarray(c1, dtype=np.float64)
    t = np.asarray(t)[..., None]
    return c0 * (1.0 - t) + c1 * t


def albedo(mat: Material, p: np.ndarray, n: np.ndarray, noise: NoiseField) -> np.ndarray:
    """Linear-RGB albedo (M, 3) in [0, 1] of ``mat`` at points ``p`` (M, 3, metres) with unit normals
    ``n`` (M, 3), both in the part's own frame."""
    p = np.asarray(p, dtype=np.float64)
    n = np.asarray(n, dtype=np.float64)
    s = mat.scale_m
    A, B = mat.color_a, mat.color_b
    k = mat.kind
    if len(p) == 0:
        return np.zeros((0, 3))
    if k == "plaster":
        t = noise.fbm(p, s, 4, mat.salt)
        out = _mix(A, B, np.clip((t - 0.3) * 1.6, 0, 1))
        out *= (0.9 + 0.2 * noise.fbm(p, s / 6, 2, mat.salt + 3.0))[:, None]
    elif k == "planks":
        a, b = _planar_coords(p, n)
        row = np.floor(b / s)
        plank_len = 6.0 * s
        shift = _hash01(row, 1) * plank_len
        col = np.floor((a + shift) / plank_len)
        fb = b / s - row  # 0..1 across the plank
        fa = (a + shift) / plank_len - col
        gap = np.minimum(_smooth_edge(fb - 0.03, 0.03) * _smooth_edge(0.97 - fb, 0.03),
                         _smooth_edge(fa - 0.005, 0.006) * _smooth_edge(0.995 - fa, 0.006))
        tint = _hash01(row, col, 2)
        # Grain follows the plank (stretched noise along it), offset per plank row.
        q = np.stack([a * 0.15, b, row], 1)
        grain = 0.5 + 0.5 * np.sin(2 * np.pi * (fb * 3.0 + 2.5 * noise.fbm(q, 0.15, 3, mat.salt)))
        base = _mix(A, B, 0.25 + 0.5 * tint)
        out = base * (0.8 + 0.25 * grain)[:, None]
        out = out * (0.35 + 0.65 * gap)[:, None]
    elif k == "wood":
        # Rings around the local x axis, distorted by noise; grain along x.
        # (the log's axis lies 0.3 m below the board, so boards show long, gently curving grain)
        r = np.hypot(p[:, 1], p[:, 2] + 0.3) / s + 0.6 * noise.fbm(p * [0.15, 1, 1], s, 3, mat.salt)
        ring = 0.5 + 0.5 * np.sin(2 * np.pi * r * 3.0)
        out = _mix(A, B, 0.6 * ring * ring)
        out *= (0.85 + 0.3 * noise.fbm(p * [0.08, 1, 1], s / 3, 2, mat.salt + 1))[:, None]
    elif k == "brick":
        a, b = _planar_coords(p, n)
        h = 0.5 * s  # course height (brick + mortar)
        row = np.floor(b / h)
        aa = a + 0.5 * s * (row % 2)
        col = np.floor(aa / s)
        fa, fb = aa / s - col, b / h - row
        mortar_w = 0.012
        inner = (_smooth_edge(fa * s - mortar_w, 0.006) * _smooth_edge((1 - fa) * s - 0.0, 0.006) *
                 _smooth_edge(fb * h - mortar_w, 0.006) * _smooth_edge((1 - fb) * h - 0.0, 0.006))
        tint = _hash01(row, col, 3)
        brick = _mix(A, np.asarray(A) * 0.6, tint) * (0.85 + 0.3 * noise.fbm(p, 0.05, 3, mat.salt))[:, None]
        mortar = np.asarray(B) * (0.9 + 0.2 * noise.fbm(p, 0.03, 2, mat.salt + 2))[:, None]
        out = mortar * (1 - inner)[:, None] + brick * inner[:, None]
    elif k == "wallpaper":
        # Vertical stripes with a repeating diamond motif, slightly worn.
        a, b = _planar_coords(p, n)
        stripe = _smooth_edge(np.abs(((a / s) % 1.0) - 0.5) - 0.25, 0.03)
        da = np.abs(((a / s + 0.5) % 1.0) - 0.5) * s
        db = np.abs(((b / (1.5 * s)) % 1.0) - 0.5) * 1.5 * s
        diamond = _smooth_edge(0.25 * s - (da + db / 1.5), 0.004)
        out = _mix(A, B, 0.55 * stripe)
        out = _mix_rows(out, np.asarray(B) * 0.7, 0.8 * diamond)
        out *= (0.9 + 0.15 * noise.fbm(p, 0.3, 3, mat.salt))[:, None]
    elif k == "checker":
        f = np.sin(np.pi * p[:, 0] / s) * np.sin(np.pi * p[:, 1] / s) * np.sin(np.pi * p[:, 2] / s + 0.5)
        t = np.clip(0.5 + 4.0 * f, 0, 1)
        out = _mix(A, B, t) * (0.9 + 0.2 * noise.fbm(p, s * 2, 3, mat.salt))[:, None]
    elif k == "cardboard":
        out = _mix(A, B, noise.fbm(p, s, 4, mat.salt))
        # packing tape along the local x axis over the top and two sides
        tape = _smooth_edge(0.025 - np.abs(p[:, 1]), 0.004) * (np.abs(n[:, 0]) < 0.5)
        out = _mix_rows(out, np.array([0.55, 0.45, 0.3]), tape * 0.8)
    elif k == "painted":
        out = np.asarray(A) * (0.92 + 0.16 * noise.fbm(p, s, 4, mat.salt))[:, None] * np.ones((len(p), 1))
    elif k == "label":
        # Cereal-box-like print: big diagonal color bands, dots and a white title block.
        a, b = _planar_coords(p, n)
        band = 0.5 + 0.5 * np.sin(2 * np.pi * (a + 0.6 * b) / s)
        out = _mix(A, B, band)
        dots = _smooth_edge(0.35 - np.hypot(((a / (s / 4)) % 1) - 0.5, ((b / (s / 4)) % 1) - 0.5), 0.08)
        out = _mix_rows(out, np.array([0.9, 0.85, 0.2]), dots * 0.7)
        title = _smooth_edge(0.02 - np.abs(b - 0.17), 0.004) * (np.abs(n[:, 2]) < 0.5)
        out = _mix_rows(out, np.array([0.95, 0.95, 0.95]), title)
        out *= (0.9 + 0.2 * noise.fbm(p, s, 3, mat.salt))[:, None]
    elif k == "bands":
        # Can label: colored bands along z, vertical stripes by azimuth, metallic-gray caps.
        z = p[:, 2]
        az = np.arctan2(p[:, 1], p[:, 0])
        band = 0.5 + 0.5 * np.sin(2 * np.pi * z / s)
        stripes = 0.5 + 0.5 * np.sin(6 * az + 3 * np.sin(2 * np.pi * z / (2 * s)))
        out = _mix(A, B, np.clip(band * 1.4 - 0.2, 0, 1))
        out = _mix_rows(out, np.array([0.95, 0.9, 0.8]), np.clip(stripes * 2 - 1.4, 0, 1))
        cap = np.abs(n[:, 2]) > 0.5
        out[cap] = np.array([0.55, 0.55, 0.58]) * (0.85 + 0.3 * noise.fbm(p[cap], 0.01, 2, mat.salt))[:, None]
    elif k == "beachball":
        az = np.arctan2(p[:, 1], p[:, 0])
        seg = (az + np.pi) / (2 * np.pi) * 6
        palette = np.array([A, B, [0.9, 0.85, 0.1], [0.1, 0.35, 0.8], [0.9, 0.9, 0.9], [0.8, 0.2, 0.5]])
        i0 = np.floor(seg).astype(int) % 6
        fr = seg - np.floor(seg)
        c0, c1 = palette[i0], palette[(i0 + 1) % 6]
        out = c0 + (c1 - c0) * _smooth_edge(fr - 1.0, 0.04)[:, None] + (c0 - c0)
        # blend across the left edge too (wrap)
        cprev = palette[(i0 - 1) % 6]
        out = out + (cprev - c0) * (1.0 - _smooth_edge(fr, 0.04))[:, None] * 0.5
        r_xy = np.hypot(p[:, 0], p[:, 1])
        pole = _smooth_edge(0.012 - r_xy, 0.006)
        out = _mix_rows(out, np.array([0.95, 0.95, 0.95]), pole)
    elif k == "stone":
        t = noise.fbm(p, s, 4, mat.salt)
        out = _mix(A, B, np.clip((t - 0.35) * 2.5, 0, 1))
        spots = _smooth_edge(noise.fbm(p, s / 3, 2, mat.salt + 5) - 0.62, 0.03)
        out = _mix_rows(out, np.array([0.85, 0.8, 0.7]), spots)
    elif k == "poster":
        a, b = _planar_coords(p, n)
        q = np.stack([a, b, np.zeros_like(a)], 1)
        rgb = np.stack([noise.fbm(q, s, 4, mat.salt + 10 * c) for c in range(3)], 1)
        out = np.clip((rgb - 0.5) * 2.2 + 0.5, 0.02, 1.0)
        out = out * np.asarray(A) + (1 - np.asarray(A)) * 0.1
    elif k == "books":
        a, b = _planar_coords(p, n)
        # Spines: columns of varying width along the first planar axis.
        u = a / s
        col = np.floor(u + 0.5 * np.sin(np.floor(u) * 1.7))
        hue = _hash01(col, 4)
        palette = np.array([[0.6, 0.1, 0.1], [0.1, 0.3, 0.6], [0.1, 0.45, 0.2], [0.75, 0.6, 0.15],
                            [0.3, 0.15, 0.4], [0.85, 0.85, 0.8], [0.15, 0.15, 0.15]])
        out = palette[np.floor(hue * len(palette)).astype(int) % len(palette)]
        frac = u + 0.5 * np.sin(np.floor(u) * 1.7) - col
        edge = _smooth_edge(frac - 0.04, 0.04) * _smooth_edge(0.96 - frac, 0.04)
        out = out * (0.55 + 0.45 * edge)[:, None] * (0.9 + 0.2 * noise.fbm(p, 0.03, 2, mat.salt))[:, None]
    elif k == "dark":
        out = np.asarray(A) * (0.8 + 0.4 * noise.fbm(p, s, 3, mat.salt))[:, None] * np.ones((len(p), 1))
    else:
        raise ValueError(f"unknown material kind {k!r}")
    return np.clip(out, 0.0, 1.0)


def _mix_rows(out: np.ndarray, c: np.ndarray, t: np.ndarray) -> np.ndarray:
    return out * (1.0 - t)[:, None] + np.asarray(c)[None, :] * t[:, None]


def _srgb_lut() -> np.ndarray:
    x = np.arange(SRGB_STEPS + 1) / SRGB_STEPS
    y = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.rint(y * 255.0).astype(np.uint8)


SRGB_STEPS = 1 << 16
SRGB_LUT = _srgb_lut()


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB uint8 (the standard transfer curve; a 65537-entry table, exact to the
    8-bit rounding except within 1e-5 of a rounding boundary)."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return SRGB_LUT[np.rint(x * SRGB_STEPS).astype(np.int64)]
