"""The one place that projects, unprojects, composes and inverts poses.

Conventions (see docs/conventions.md):
- Units: metres, seconds, radians.
- Camera frame: OpenCV (x right, y down, z forward). Pixel (u, v) = (0, 0) is the *centre* of the
  top-left pixel, so pixel (u, v) covers [u-0.5, u+0.5] x [v-0.5, v+0.5].
- Poses: ``T_a_b`` is a 4x4 homogeneous matrix mapping points from frame b to frame a
  (``p_a = T_a_b @ p_b``); ``T_world_cam`` is camera-to-world. Composition reads left to right:
  ``T_world_obj = compose(T_world_cam, T_cam_obj)``.
- Depth: float32 z-depth in metres (distance along the optical axis), 0 = invalid.
- Quaternions are ``quat_xyzw`` (scalar last, as ROS and TUM files write them).

Every function here accepts batched inputs with leading dimensions ``(..., 4, 4)`` / ``(..., 3)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Intrinsics",
    "compose",
    "invert",
    "transform_points",
    "project",
    "unproject",
    "unproject_depth",
    "pixel_grid",
    "make_pose",
    "quat_xyzw_to_R",
    "R_to_quat_xyzw",
    "pose_from_tum",
    "pose_to_tum",
    "check_rigid",
    "ORTHONORMAL_EXACT_TOL",
    "rotation_angle_rad",
    "rotation_z",
    "look_at",
    "T_CV_FROM_GL",
]

# OpenGL/nerfstudio camera (x right, y up, z backward) -> OpenCV camera (x right, y down, z forward).
# Applied on the right of a camera-to-world pose: T_world_cv = T_world_gl @ T_CV_FROM_GL
# (named for readability; as a transform it is T_gl_cv).
T_CV_FROM_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an undistorted image of ``width`` x ``height`` pixels.

    Example:
        >>> K = Intrinsics(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
        >>> K.hfov_deg  # doctest: +ELLIPSIS
        65.2...
    """

    fx: float
    """Focal length along x, pixels."""
    fy: float
    """Focal length along y, pixels."""
    cx: float
    """Principal point x, pixels (pixel centres at integers)."""
    cy: float
    """Principal point y, pixels."""
    width: int
    """Image width, pixels."""
    height: int
    """Image height, pixels."""

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in vals):
            raise ValueError(f"intrinsics must be finite, got {vals}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx} fy={self.fy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def size_wh(self) -> tuple[int, int]:
        return (self.width, self.height)

    @property
    def hfov_deg(self) -> float:
        return float(np.degrees(2.0 * np.arctan2(self.width / 2.0, self.fx)))

    @property
    def vfov_deg(self) -> float:
        return float(np.degrees(2.0 * np.arctan2(self.height / 2.0, self.fy)))

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int, source: str = "") -> "Intrinsics":
        """From a 3x3 camera matrix of a ``width`` x ``height`` image. The principal point must lie
        inside the image: one outside it means the matrix belongs to another resolution (``source``,
        e.g. the intrinsics file, prefixes the error)."""
        where = f"{source}: " if source else ""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"{where}K must be 3x3, got shape {K.shape}")
        cx, cy = K[0, 2], K[1, 2]
        if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
            raise ValueError(f"{where}principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} "
                             "image: intrinsics of another resolution?")
        return cls(K[0, 0], K[1, 1], cx, cy, width, height)

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> "Intrinsics":
        """Square pixels, principal point at the image centre."""
        f = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """Intrinsics of the same camera resampled to ``width`` x ``height`` (pixel-centre aware)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5,
            width, height,
        )

    def to_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, d: dict) -> "Intrinsics":
        return cls(d["fx"], d["fy"], d["cx"], d["cy"], d["width"], d["height"])


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 pose from rotation ``R`` (...,3,3) and translation ``t`` (...,3)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def compose(T_a_b: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """``T_a_c = T_a_b @ T_b_c`` (broadcasts over leading dimensions)."""
    return np.asarray(T_a_b, dtype=np.float64) @ np.asarray(T_b_c, dtype=np.float64)


def invert(T_a_b: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform: ``T_b_a``. Uses R^T, exact for rotations."""
    T_a_b = np.asarray(T_a_b, dtype=np.float64)
    if T_a_b.shape == (4, 4):
        # One pose (every frame of the renderer): on Python floats, the same products summed in
        # the same order as the einsum below (bit for bit, tested), without its cold numpy calls.
        (r00, r01, r02, t0), (r10, r11, r12, t1), (r20, r21, r22, t2), _ = T_a_b.tolist()
        return np.array(((r00, r10, r20, -(r00 * t0 + r10 * t1 + r20 * t2)),
                         (r01, r11, r21, -(r01 * t0 + r11 * t1 + r21 * t2)),
                         (r02, r12, r22, -(r02 * t0 + r12 * t1 + r22 * t2)),
                         (0.0, 0.0, 0.0, 1.0)))
    R = T_a_b[..., :3, :3]
    t = T_a_b[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    return make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, t))


def transform_points(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Apply ``T_a_b`` (4x4) to points ``p_b`` (..., 3) -> ``p_a`` (..., 3), dtype of the points."""
    T = np.asarray(T_a_b, dtype=np.float64)
    p = np.asarray(p_b)
    out = p.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    return out.astype(p.dtype if np.issubdtype(p.dtype, np.floating) else np.float64)


def project(K: Intrinsics, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points (..., 3) to pixels.

    Returns ``(uv, depth_m)``: ``uv`` (..., 2) in pixels with (0, 0) the centre of the top-left
    pixel, and z-depth (...,). Points with z <= 0 get ``uv = nan``.
    """
    p = np.asarray(p_cam, dtype=np.float64)
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K.fx * p[..., 0] / z + K.cx
        v = K.fy * p[..., 1] / z + K.cy
    uv = np.stack([u, v], axis=-1)
    uv[z <= 0] = np.nan
    return uv, z


def unproject(K: Intrinsics, uv: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """Pixels ``uv`` (..., 2) with z-depth (...,) -> camera-frame points (..., 3)."""
    uv = np.asarray(uv, dtype=np.float64)
    z = np.asarray(depth_m, dtype=np.float64)
    x = (uv[..., 0] - K.cx) / K.fx * z
    y = (uv[..., 1] - K.cy) / K.fy * z
    return np.stack([x, y, z], axis=-1)


def pixel_grid(width: int, height: int) -> np.ndarray:
    """(H, W, 2) float32 array of pixel centres (u, v)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    return np.stack([u, v], axis=-1)


def unproject_depth(K: Intrinsics, depth_m: np.ndarray, T_world_cam: np.ndarray | None = None,
                    stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Back-project a depth map to 3D points (float32).

    Args:
        K: intrinsics of the depth map (``depth_m`` is H x W = K.height x K.width).
        depth_m: z-depth in metres, 0 = invalid.
        T_world_cam: when given, points are returned in the world frame, else in the camera frame.
        stride: take every ``stride``-th pixel in u and v.

    Returns:
        ``(points, mask)``: points (N, 3) for valid pixels and the (H/stride, W/stride) validity mask.
    """
    d = np.asarray(depth_m)[::stride, ::stride]
    if np.asarray(depth_m).shape != (K.height, K.width):
        raise ValueError(f"depth shape {np.asarray(depth_m).shape} != intrinsics {K.height}x{K.width}")
    mask = np.isfinite(d) & (d > 0)
    vs, us = np.nonzero(mask)
    uv = np.stack([us * stride, vs * stride], axis=-1).astype(np.float64)
    pts = unproject(K, uv, d[vs, us])
    if T_world_cam is not None:
        pts = transform_points(T_world_cam, pts)
    return pts.astype(np.float32), mask


# ---- rotations ---------------------------------------------------------------------------------

def quat_xyzw_to_R(q_xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternion (..., 4) scalar-last -> rotation (..., 3, 3). The input is normalised."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(~np.isfinite(n)) or np.any(n < 1e-9):
        raise ValueError("quaternion must be finite and non-zero")
    x, y, z, w = np.moveaxis(q / n, -1, 0)
    R = np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], axis=-1)
    return R.reshape(q.shape[:-1] + (3, 3))


def R_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) -> unit quaternion (4,) scalar-last with w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def pose_from_tum(values: np.ndarray) -> np.ndarray:
    """``[x y z qx qy qz qw]`` (..., 7) -> 4x4 pose (TUM trajectory line without the timestamp)."""
    v = np.asarray(values, dtype=np.float64)
    if v.shape[-1] != 7:
        raise ValueError(f"a TUM pose has 7 numbers (x y z qx qy qz qw), got {v.shape[-1]}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"pose contains non-finite values: {v}")
    return make_pose(quat_xyzw_to_R(v[..., 3:]), v[..., :3])


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """4x4 pose -> ``[x y z qx qy qz qw]``."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[:3, 3], R_to_quat_xyzw(T[:3, :3])])


ORTHONORMAL_EXACT_TOL = 1e-12
""":func:`check_rigid` returns a rotation with ``max |R R^T - I|`` at most this as it is (it is
orthonormal to float64 rounding already), others re-orthonormalised by SVD."""


def check_rigid(T: np.ndarray, what: str = "pose", tol: float = 1e-3) -> np.ndarray:
    """Validate a 4x4 rigid transform; raise ``ValueError`` naming ``what`` otherwise.

    Returns the pose as a float64 copy, the rotation re-orthonormalised (SVD) when it is within
    ``tol`` but not already orthonormal to rounding (``max |R R^T - I|`` > :data:`ORTHONORMAL_EXACT_TOL`).

    The tests run on the 16 numbers as Python floats: the renderer checks every target pose, and
    there the numpy / LAPACK calls of the same tests took ~0.2 ms per frame (their code cold in
    the caches after the frame's kernels), against a few µs.
    """
    T = np.array(T, dtype=np.float64)  # a copy (the caller's array is never returned)
    if T.shape != (4, 4):
        raise ValueError(f"{what}: expected a 4x4 matrix, got shape {T.shape}")
    (r00, r01, r02, t0), (r10, r11, r12, t1), (r20, r21, r22, t2), (a, b, c, d) = T.tolist()
    vals = (r00, r01, r02, t0, r10, r11, r12, t1, r20, r21, r22, t2, a, b, c, d)
    if not all(map(math.isfinite, vals)):
        raise ValueError(f"{what}: contains non-finite values (NaN/inf)")
    # = np.allclose(T[3], [0, 0, 0, 1], atol=1e-6) (its |a - b| <= atol + rtol |b|), without its overhead
    if not (abs(a) <= 1e-6 and abs(b) <= 1e-6 and abs(c) <= 1e-6 and abs(d - 1.0) <= 1e-6 + 1e-5 * 1.0):
        raise ValueError(f"{what}: last row must be [0 0 0 1], got {T[3]}")
    rows = ((r00, r01, r02), (r10, r11, r12), (r20, r21, r22))
    err = max(abs(rows[i][0] * rows[j][0] + rows[i][1] * rows[j][1] + rows[i][2] * rows[j][2] - (i == j))
              for i in range(3) for j in range(i, 3))  # max |R R^T - I| (symmetric)
    det = r00 * (r11 * r22 - r12 * r21) - r01 * (r10 * r22 - r12 * r20) + r02 * (r10 * r21 - r11 * r20)
    if err > tol or det < 0:
        raise ValueError(f"{what}: rotation is not orthonormal (max |R R^T - I| = {err:.3g}, det = {det:.3g})")
    if err > ORTHONORMAL_EXACT_TOL:
        U, _, Vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = U @ Vt
    return T


def rotation_angle_rad(R_a: np.ndarray, R_b: np.ndarray | None = None) -> np.ndarray:
    """Angle of the rotation ``R_a`` (or of ``R_a^T R_b``), radians, numerically clipped."""
    R = np.asarray(R_a, dtype=np.float64)
    if R_b is not None:
        R = np.swapaxes(R, -1, -2) @ np.asarray(R_b, dtype=np.float64)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    # Avoid invalid values due to numerical errors.
    return np.arccos(np.clip(c, -1.0, 1.0))


def rotation_z(yaw_rad: float) -> np.ndarray:
    """3x3 rotation about +z by ``yaw_rad``."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_cam`` of an OpenCV camera at ``eye`` looking at ``target`` with world ``up``."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), eye)
