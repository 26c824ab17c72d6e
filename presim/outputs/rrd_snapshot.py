"""A still image of a recorded ``.rrd`` (``presim view FILE.rrd --screenshot out.png``): the scene's
point cloud, the input camera positions, the base and camera trajectories and the robot's final pose
in 3D, beside the last colour and depth images the robot's camera saw. For a user on a server with no
display or browser: it reads the file with rerun's chunk reader and draws with matplotlib (Agg).

The 3D view is turned so that "up" is the mean up axis (-y of the OpenCV frame) of the input cameras:
the floor's normal in a scene with a floor, and the best guess the importer also uses in one without.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from presim.io_utils import atomic_write_bytes

__all__ = ["RrdContent", "read_rrd", "write_snapshot"]

MAX_POINTS = 30_000
"""Scene points drawn at most (a random subset; matplotlib's 3D scatter takes ~1 s for 30 k)."""
_CAMERA_TAIL = "camera_optical_frame"


@dataclass
class RrdContent:
    """What :func:`write_snapshot` draws, read from an ``.rrd`` written by :class:`~presim.outputs.viewer.RerunViewer`."""

    points_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    points_rgb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    input_T_world_cam: list[np.ndarray] = field(default_factory=list)
    """4x4 poses of the scene's input views."""
    base_path: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    camera_path: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    T_world_base: np.ndarray | None = None
    """The robot's last logged base pose."""
    color: np.ndarray | None = None
    """The last colour image (H, W, 3) uint8."""
    depth_m: np.ndarray | None = None
    """The last depth image (H, W) float32 metres."""
    steps: int = 0
    """Largest step index in the file."""


def _last(rb, name: str):
    """Column ``name`` of a record batch at its latest row (largest ``step``, else the last row with a
    value), as Python objects; None when absent."""
    if name not in rb.schema.names:
        return None
    col = rb.column(name).to_pylist()
    rows = [i for i, v in enumerate(col) if v is not None]
    if not rows:
        return None
    if "step" in rb.schema.names:
        step = rb.column("step").to_pylist()
        return col[max(rows, key=lambda i: (step[i] if step[i] is not None else -1, i))]
    return col[rows[-1]]


def _step(rb) -> int:
    return int(_last(rb, "step") or -1) if "step" in rb.schema.names else -1


def _pose(rb) -> np.ndarray | None:
    R, t = _last(rb, "Transform3D:mat3x3"), _last(rb, "Transform3D:translation")
    if R is None or t is None:
        return None
    T = np.eye(4)
    T[:3, :3] = np.asarray(R[0], dtype=np.float64).reshape(3, 3, order="F")  # rerun: column-major
    T[:3, 3] = t[0]
    return T


def _image(rb, kind: str) -> np.ndarray | None:
    """The latest image of a chunk: raw ``Image`` / ``DepthImage`` buffers or a JPEG/PNG ``EncodedImage``."""
    blob = _last(rb, "EncodedImage:blob")
    if kind == "Image" and blob is not None:
        import cv2

        bgr = cv2.imdecode(np.frombuffer(bytes(blob[0]), np.uint8), cv2.IMREAD_COLOR)
        return None if bgr is None else bgr[..., ::-1].copy()
    buf, fmt = _last(rb, f"{kind}:buffer"), _last(rb, f"{kind}:format")
    if buf is None or fmt is None:
        return None
    w, h = fmt[0]["width"], fmt[0]["height"]
    dtype = np.float32 if kind == "DepthImage" else np.uint8
    a = np.frombuffer(bytes(buf[0]), dtype=dtype)
    ch = a.size // (w * h)
    if ch * w * h != a.size or (kind == "Image" and ch not in (1, 3, 4)):
        return None
    a = a.reshape(h, w, ch) if ch > 1 else a.reshape(h, w)
    return a[..., :3] if kind == "Image" and ch == 4 else a


def read_rrd(path: str | Path) -> RrdContent:
    """Read what the snapshot draws from ``path``; ValueError naming the file when rerun cannot read it."""
    try:
        from rerun.chunk import RrdReader

        chunks = list(RrdReader(str(path)).stream())
    except ImportError:
        raise
    except Exception as e:  # noqa: BLE001 - rerun raises its own types for corrupt files
        raise ValueError(f"{path}: not a readable .rrd recording ({e})") from e
    out = RrdContent()
    inputs: dict[str, np.ndarray] = {}
    latest: dict[str, int] = {}  # what -> step of the value kept (chunks need not come in step order)

    def newer(what: str, rb) -> bool:
        s = _step(rb)
        if s < latest.get(what, -2):
            return False
        latest[what] = s
        return True

    for c in chunks:
        ent, rb = c.entity_path, c.to_record_batch()
        out.steps = max(out.steps, _step(rb))
        if ent == "/world/scene":
            pos = _last(rb, "Points3D:positions")
            if pos:
                out.points_xyz = np.asarray(pos, dtype=np.float32)
                col = _last(rb, "Points3D:colors")
                if col and len(col) == len(pos):  # packed 0xRRGGBBAA
                    u = np.asarray(col, dtype=np.uint32)
                    out.points_rgb = np.stack([(u >> 24) & 255, (u >> 16) & 255, (u >> 8) & 255], 1).astype(np.uint8)
        elif ent.startswith("/world/inputs/"):
            T = _pose(rb)
            if T is not None:
                inputs[ent] = T
        elif ent in ("/world/trajectory/base", "/world/trajectory/camera"):
            strips = _last(rb, "LineStrips3D:strips")
            name = "base_path" if ent.endswith("base") else "camera_path"
            if strips and len(strips[0]) >= len(getattr(out, name)):  # the path only grows: keep the longest
                setattr(out, name, np.asarray(strips[0], dtype=np.float64).reshape(-1, 3))
        elif ent.startswith("/world/robot/") and ent.rsplit("/", 1)[-1] == "base_link" and not c.is_static:
            T = _pose(rb)
            if T is not None and newer("base", rb):
                out.T_world_base = T
        elif ent.endswith(f"{_CAMERA_TAIL}/color"):
            img = _image(rb, "Image")
            if img is not None and newer("color", rb):
                out.color = img
        elif ent.endswith(f"{_CAMERA_TAIL}/depth"):
            d = _image(rb, "DepthImage")
            if d is not None and newer("depth", rb):
                out.depth_m = d
    out.input_T_world_cam = [inputs[k] for k in sorted(inputs)]
    return out


def _up_rotation(Ts: list[np.ndarray]) -> np.ndarray:
    """R_view_world turning the input cameras' mean up axis to +z (identity without inputs)."""
    if not Ts:
        return np.eye(3)
    up = -np.mean([T[:3, 1] for T in Ts], axis=0)
    n = np.linalg.norm(up)
    if n < 1e-6:
        return np.eye(3)
    up /= n
    v, c = np.cross(up, [0.0, 0.0, 1.0]), float(up[2])
    if np.linalg.norm(v) < 1e-9:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def write_snapshot(rrd_path: str | Path, png_path: str | Path, size_px: tuple[int, int] = (1600, 900),
                   seed: int = 0) -> RrdContent:
    """Draw the recording ``rrd_path`` into ``png_path`` (written atomically); returns what was read.
    ``seed`` picks the subset of scene points drawn when there are more than :data:`MAX_POINTS`."""
    import io

    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    rec = read_rrd(rrd_path)
    R = _up_rotation(rec.input_T_world_cam)
    fig = plt.figure(figsize=(size_px[0] / 100, size_px[1] / 100), dpi=100)
    ax = fig.add_axes((0.0, 0.0, 0.6, 0.95), projection="3d")
    pts = rec.points_xyz
    if len(pts):
        idx = np.random.default_rng(seed).permutation(len(pts))[:MAX_POINTS]
        p = pts[idx] @ R.T
        rgb = rec.points_rgb[idx] / 255.0 if len(rec.points_rgb) == len(pts) else "0.5"
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=rgb, s=1.0, depthshade=False, linewidths=0)
    if rec.input_T_world_cam:
        c = np.array([T[:3, 3] for T in rec.input_T_world_cam]) @ R.T
        ax.scatter(c[:, 0], c[:, 1], c[:, 2], c="k", s=8, marker="^", label="input views")
    for path_xyz, color, label in ((rec.base_path, "tab:red", "base path"), (rec.camera_path, "orange", "camera path")):
        if len(path_xyz):
            q = path_xyz @ R.T
            ax.plot(q[:, 0], q[:, 1], q[:, 2], color=color, lw=2, label=label)
    if rec.T_world_base is not None:
        o = R @ rec.T_world_base[:3, 3]
        ax.scatter(*o, c="tab:red", s=80, marker="o", label="robot (last pose)")
        for axis, col in zip(range(3), ("r", "g", "b")):
            d = R @ rec.T_world_base[:3, axis] * 0.15
            ax.quiver(*o, *d, color=col, lw=2)
    drawn = [a for a in (pts, rec.base_path, rec.camera_path) if len(a)]
    _equal_axes(ax, np.concatenate(drawn) @ R.T if drawn else np.zeros((1, 3)))
    ax.view_init(elev=35, azim=-60)
    ax.set_title(f"{Path(rrd_path).name}: scene, trajectory and robot ({rec.steps} steps)")
    ax.legend(loc="upper left", fontsize=8)
    for k, (img, title) in enumerate(((rec.color, "last colour image"), (rec.depth_m, "last depth (m)"))):
        a = fig.add_axes((0.62, 0.52 - 0.48 * k, 0.36, 0.42))
        a.set_axis_off()
        a.set_title(title, fontsize=9)
        if img is None:
            a.text(0.5, 0.5, "none recorded", ha="center", va="center")
        elif img.ndim == 2:
            fig.colorbar(a.imshow(img, cmap="viridis", vmin=0.0), ax=a, fraction=0.046)
        else:
            a.imshow(img)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(png_path, buf.getvalue())
    return rec


def _equal_axes(ax, xyz: np.ndarray) -> None:
    lo, hi = np.percentile(xyz, 1, axis=0), np.percentile(xyz, 99, axis=0)  # stray points do not zoom out
    c, r = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 0.1)
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("up (m)")
