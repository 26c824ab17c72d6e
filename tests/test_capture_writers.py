"""Small capture writers shared by the importer tests (each format written from the same frames),
plus checks of the writers themselves."""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from presim.geometry import T_CV_FROM_GL, Intrinsics, R_to_quat_xyzw, compose, invert, look_at, pose_to_tum
from presim.io_utils import write_png


@dataclass
class SynthFrames:
    K: Intrinsics
    color: np.ndarray       # (N, H, W, 3) uint8
    depth_mm: np.ndarray    # (N, H, W) uint16, 0 = invalid
    T_world_cam: np.ndarray  # (N, 4, 4)

    @property
    def depth_m(self) -> np.ndarray:
        return self.depth_mm.astype(np.float32) * np.float32(1e-3)

    def __len__(self) -> int:
        return len(self.color)


def synth_frames(n: int = 4, w: int = 40, h: int = 30, seed: int = 0) -> SynthFrames:
    """Random but valid frames: textured color, depth 0.5-3 m with ~10 % holes, rigid poses looking
    at the origin from a ring (camera up = world +z)."""
    rng = np.random.default_rng(seed)
    K = Intrinsics(50.0, 52.0, (w - 1) / 2 + 0.3, (h - 1) / 2 - 0.2, w, h)
    color = rng.integers(0, 256, size=(n, h, w, 3), dtype=np.uint8)
    depth = rng.integers(500, 3000, size=(n, h, w)).astype(np.uint16)
    depth[rng.random((n, h, w)) < 0.1] = 0
    poses = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([2.0 * np.cos(a), 2.0 * np.sin(a), 1.2 + 0.1 * i])
        poses.append(look_at(eye, np.array([0.1, -0.2, 0.3])))
    return SynthFrames(K, color, depth, np.stack(poses))


# ---- writers ----------------------------------------------------------------------------------
def write_kinfu(dst: Path, f: SynthFrames, intrinsics_name: str = "camera-intrinsics.txt",
                timestamps: bool = True, jpg: bool = False) -> Path:
    dst.mkdir(parents=True, exist_ok=True)
    np.savetxt(dst / intrinsics_name, f.K.K)
    lines = []
    for i in range(len(f)):
        fid = f"frame-{i:06d}"
        if jpg:
            import cv2

            cv2.imwrite(str(dst / f"{fid}.color.jpg"), f.color[i][..., ::-1])
        else:
            write_png(dst / f"{fid}.color.png", f.color[i])
        write_png(dst / f"{fid}.depth.png", f.depth_mm[i])
        np.savetxt(dst / f"{fid}.pose.txt", f.T_world_cam[i], fmt="%.17g")
        lines.append(f"{fid} {100.0 + 0.1 * i:.6f}")
    if timestamps:
        (dst / "timestamps.txt").write_text("\n".join(lines) + "\n")
    return dst


def tum_stamps(n: int) -> np.ndarray:
    return 1305031102.0 + 0.1 * np.arange(n)


def write_tum(dst: Path, f: SynthFrames) -> Path:
    """TUM sequence with depth stamps 5 ms after rgb and ground truth at 100 Hz bracketing them."""
    dst.mkdir(parents=True, exist_ok=True)
    (dst / "rgb").mkdir(exist_ok=True)
    (dst / "depth").mkdir(exist_ok=True)
    st = tum_stamps(len(f))
    rgb, dep, gt = ["# color images", "# file: 'x.bag'", "# timestamp filename"], ["# depth"], ["# gt"]
    for i, t in enumerate(st):
        write_png(dst / "rgb" / f"{t:.6f}.png", f.color[i])
        # TUM depth is 1/5000 m: mm * 5
        write_png(dst / "depth" / f"{t + 0.005:.6f}.png", (f.depth_mm[i].astype(np.uint32) * 5).astype(np.uint16))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        dep.append(f"{t + 0.005:.6f} depth/{t + 0.005:.6f}.png")
        # exact pose at the rgb stamp plus perturbed-free neighbours: same pose 10 ms before/after
        for dt in (-0.01, 0.0, 0.01):
            v = pose_to_tum(f.T_world_cam[i])
            gt.append(f"{t + dt:.6f} " + " ".join(f"{x:.17g}" for x in v))
    (dst / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (dst / "depth.txt").write_text("\n".join(dep) + "\n")
    (dst / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    np.savetxt(dst / "camera-intrinsics.txt", f.K.K)
    return dst


def write_nerfstudio(dst: Path, f: SynthFrames, per_frame_intrinsics: bool = False, npy_depth: bool = False) -> Path:
    dst.mkdir(parents=True, exist_ok=True)
    (dst / "images").mkdir(exist_ok=True)
    (dst / "depth").mkdir(exist_ok=True)
    # nerfstudio's pixel origin is the corner: cx_ns = cx + 0.5
    intr = {"fl_x": f.K.fx, "fl_y": f.K.fy, "cx": f.K.cx + 0.5, "cy": f.K.cy + 0.5, "w": f.K.width,
            "h": f.K.height, "camera_model": "PINHOLE"}
    frames = []
    for i in range(len(f)):
        write_png(dst / "images" / f"frame_{i:05d}.png", f.color[i])
        if npy_depth:
            np.save(dst / "depth" / f"frame_{i:05d}.npy", f.depth_mm[i].astype(np.float32))
            dpath = f"depth/frame_{i:05d}.npy"
        else:
            write_png(dst / "depth" / f"frame_{i:05d}.png", f.depth_mm[i])
            dpath = f"depth/frame_{i:05d}.png"
        T_gl = compose(f.T_world_cam[i], invert(T_CV_FROM_GL))  # OpenCV -> OpenGL camera
        fr = {"file_path": f"images/frame_{i:05d}.png", "depth_file_path": dpath,
              "transform_matrix": T_gl.tolist()}
        if per_frame_intrinsics:
            fr.update(intr)
        frames.append(fr)
    meta = {} if per_frame_intrinsics else dict(intr)
    meta["frames"] = frames
    (dst / "transforms.json").write_text(json.dumps(meta))
    return dst


def _colmap_images(f: SynthFrames):
    out = []
    for i in range(len(f)):
        T_cw = invert(f.T_world_cam[i])
        q = R_to_quat_xyzw(T_cw[:3, :3])
        out.append((i + 1, np.r_[q[3], q[:3]], T_cw[:3, 3], 1, f"img_{i:04d}.png"))
    return out


def write_colmap(dst: Path, f: SynthFrames, binary: bool = False, model: str = "PINHOLE",
                 dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0), npy_depth: bool = True) -> Path:
    sparse = dst / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    (dst / "images").mkdir(exist_ok=True)
    (dst / "depths").mkdir(exist_ok=True)
    K = f.K
    # COLMAP's pixel origin is the corner: cx_colmap = cx + 0.5
    if model == "SIMPLE_PINHOLE":
        params, mid = [K.fx, K.cx + 0.5, K.cy + 0.5], 0
    elif model == "PINHOLE":
        params, mid = [K.fx, K.fy, K.cx + 0.5, K.cy + 0.5], 1
    elif model == "OPENCV":
        params, mid = [K.fx, K.fy, K.cx + 0.5, K.cy + 0.5, *dist], 4
    else:  # an unsupported one for the error test
        params, mid = [K.fx, K.cx + 0.5, K.cy + 0.5, 0.01], 2
    images = _colmap_images(f)
    pts = np.array([[0.1, 0.2, 0.3], [1.0, -1.0, 0.5]])
    for i, (_, _, _, _, name) in enumerate(images):
        write_png(dst / "images" / name, f.color[i])
        if npy_depth:
            np.save(dst / "depths" / f"{Path(name).stem}.npy", f.depth_m[i])
        else:
            write_png(dst / "depths" / f"{Path(name).stem}.png", f.depth_mm[i])
    if binary:
        with open(sparse / "cameras.bin", "wb") as fh:
            fh.write(struct.pack("<Q", 1))
            fh.write(struct.pack("<iiQQ", 1, mid, K.width, K.height))
            fh.write(struct.pack(f"<{len(params)}d", *params))
        with open(sparse / "images.bin", "wb") as fh:
            fh.write(struct.pack("<Q", len(images)))
            for iid, q, t, cid, name in images:
                fh.write(struct.pack("<idddddddi", iid, *q, *t, cid))
                fh.write(name.encode() + b"\x00")
                fh.write(struct.pack("<Q", 1))
                fh.write(struct.pack("<ddq", 3.0, 4.0, -1))
        with open(sparse / "points3D.bin", "wb") as fh:
            fh.write(struct.pack("<Q", len(pts)))
            for k, p in enumerate(pts):
                fh.write(struct.pack("<QdddBBBdQ", k + 1, *p, 10, 20, 30, 0.5, 1))
                fh.write(struct.pack("<ii", 1, 0))
    else:
        names = {0: "SIMPLE_PINHOLE", 1: "PINHOLE", 4: "OPENCV", 2: "SIMPLE_RADIAL"}
        (sparse / "cameras.txt").write_text(
            "# Camera list\n" + f"1 {names[mid]} {K.width} {K.height} " + " ".join(f"{p:.17g}" for p in params) + "\n")
        lines = ["# Image list"]
        for iid, q, t, cid, name in images:
            lines.append(f"{iid} " + " ".join(f"{x:.17g}" for x in (*q, *t)) + f" {cid} {name}")
            lines.append("3.0 4.0 -1")
        (sparse / "images.txt").write_text("\n".join(lines) + "\n")
        (sparse / "points3D.txt").write_text(
            "# 3D points\n" + "".join(f"{k + 1} {p[0]} {p[1]} {p[2]} 10 20 30 0.5 1 0\n" for k, p in enumerate(pts)))
    return dst


def write_bop(dst_scene: Path, f: SynthFrames, depth_scale: float = 0.1, with_w2c: bool = True,
              objects: bool = True) -> Path:
    """BOP scene DATASET/test/000001 (+ DATASET/models with a tetrahedron in mm)."""
    dst_scene.mkdir(parents=True, exist_ok=True)
    (dst_scene / "rgb").mkdir(exist_ok=True)
    (dst_scene / "depth").mkdir(exist_ok=True)
    T_world_obj = look_at(np.array([0.1, 0.0, 0.05]), np.array([1.0, 0.3, 0.05]))
    cams, gt = {}, {}
    for i in range(len(f)):
        im = 3 * i + 1
        write_png(dst_scene / "rgb" / f"{im:06d}.png", f.color[i])
        # depth_mm = value * depth_scale -> value = mm / scale
        write_png(dst_scene / "depth" / f"{im:06d}.png", np.round(f.depth_mm[i] / depth_scale).astype(np.uint16))
        T_cw = invert(f.T_world_cam[i])
        e = {"cam_K": f.K.K.ravel().tolist(), "depth_scale": depth_scale}
        if with_w2c:
            e["cam_R_w2c"] = T_cw[:3, :3].ravel().tolist()
            e["cam_t_w2c"] = (T_cw[:3, 3] * 1000).tolist()
        cams[str(im)] = e
        T_co = compose(T_cw, T_world_obj)
        gt[str(im)] = [{"cam_R_m2c": T_co[:3, :3].ravel().tolist(), "cam_t_m2c": (T_co[:3, 3] * 1000).tolist(),
                        "obj_id": 7}]
    (dst_scene / "scene_camera.json").write_text(json.dumps(cams))
    if objects:
        (dst_scene / "scene_gt.json").write_text(json.dumps(gt))
        models = dst_scene.parent.parent / "models"
        models.mkdir(parents=True, exist_ok=True)
        (models / "obj_000007.ply").write_text(
            "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 4\nproperty list uchar int vertex_indices\nend_header\n"
            "0 0 0\n100 0 0\n0 100 0\n0 0 100\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")
    return dst_scene


BOP_T_WORLD_OBJ = look_at(np.array([0.1, 0.0, 0.05]), np.array([1.0, 0.3, 0.05]))


# ---- sanity of the writers themselves ---------------------------------------------------------
def test_synth_frames_are_valid():
    f = synth_frames()
    assert f.color.dtype == np.uint8 and f.depth_mm.dtype == np.uint16
    assert 0.05 < (f.depth_mm == 0).mean() < 0.2
    for T in f.T_world_cam:
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)


def test_kinfu_writer_files(tmp_path):
    d = write_kinfu(tmp_path / "k", synth_frames(n=2))
    assert sorted(p.name for p in d.iterdir())[:3] == ["camera-intrinsics.txt", "frame-000000.color.png",
                                                       "frame-000000.depth.png"]
