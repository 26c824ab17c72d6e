"""presim.capture.store: lossless round trip, lazy memory-mapped loading, atomic saves, version check."""

from __future__ import annotations

import json

import numpy as np
import pytest

from presim.capture.scene import (
    AppliedTransform, ArrayFrameSource, FloorPlane, PointCloud, Scene, SceneError, SceneMeta, SceneObject,
)
from presim.capture.store import FORMAT_VERSION, fuse_point_cloud, load_scene, save_scene
from presim.geometry import Intrinsics, look_at, make_pose, rotation_z


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")


def _scene(n=3, h=12, w=16, seed=0, refined=False, tmp_model=None) -> Scene:
    rng = np.random.default_rng(seed)
    color = rng.integers(0, 256, (n, h, w, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 4.0, (n, h, w)).astype(np.float32)
    depth[:, 0, 0] = 0.0
    poses = np.stack([look_at([i * 0.1, -1.0, 1.3], [0.0, 0.0, 0.8]) for i in range(n)])
    Ks = [Intrinsics(20.0 + i, 21.0, 7.5, 5.5, w, h) for i in range(n)]
    objects = []
    if tmp_model is not None:
        objects = [SceneObject(3, "box", make_pose(rotation_z(0.3), [0.1, 0.2, 0.75]), str(tmp_model), True)]
    meta = SceneMeta("test", "unit", "1", (AppliedTransform("floor_alignment", make_pose(rotation_z(0.1), [0, 0, 0.2])),),
                     notes=("a note",))
    return Scene([f"f{i}" for i in range(n)], np.arange(n) * 0.2 + 1e9, poses, Ks, ArrayFrameSource(color, depth), meta,
                 points=PointCloud(rng.normal(size=(50, 3)).astype(np.float32), rng.integers(0, 256, (50, 3), dtype=np.uint8)),
                 floor=FloorPlane((0.0, 0.0, 1.0), 0.0, 0.3), gravity_world=np.array([0.0, 0.0, -1.0]),
                 objects=objects, depth_refined=(depth * 1.01 if refined else None))


def test_round_trip_lossless(tmp_path):
    model = tmp_path / "m.ply"
    model.write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    s = _scene(refined=True, tmp_model=model)
    back = load_scene(save_scene(s, tmp_path / "scene"))
    assert back.frame_ids == s.frame_ids and back.intrinsics == s.intrinsics
    np.testing.assert_array_equal(back.stamps_s, s.stamps_s)
    np.testing.assert_array_equal(back.T_world_cam, s.T_world_cam)
    for i in range(len(s)):
        np.testing.assert_array_equal(back.frame(i).color, s.frame(i).color)
        np.testing.assert_array_equal(back.frame(i).depth_m, s.frame(i).depth_m)
        np.testing.assert_array_equal(back.depth(i, refined=True), s.depth_refined[i])
    np.testing.assert_array_equal(back.points.xyz, s.points.xyz)
    np.testing.assert_array_equal(back.points.rgb, s.points.rgb)
    assert back.floor == s.floor
    np.testing.assert_array_equal(back.gravity_world, s.gravity_world)
    assert back.meta.notes == s.meta.notes and back.meta.source == "test"
    np.testing.assert_array_equal(back.meta.transforms[0].T_new_old, s.meta.transforms[0].T_new_old)
    o, o0 = back.objects[0], s.objects[0]
    assert (o.obj_id, o.name, o.symmetric) == (3, "box", True)
    np.testing.assert_array_equal(o.T_world_obj, o0.T_world_obj)
    assert o.model_path == "objects/obj_000003.ply" and (back.path / o.model_path).read_bytes() == model.read_bytes()
    assert back.has_refined_depth
    # a second save of the loaded scene is identical again (relative model path resolved)
    again = load_scene(save_scene(back, tmp_path / "scene2"))
    np.testing.assert_array_equal(again.frames.color, back.frames.color)


def test_load_is_lazy_memmap(tmp_path):
    back = load_scene(save_scene(_scene(), tmp_path / "scene"))
    assert isinstance(back.frames.color, np.memmap) and isinstance(back.frames.depth_m, np.memmap)
    assert back.frames.color.mode == "r"  # read-only: a consumer cannot corrupt the scene
    with pytest.raises(ValueError):
        back.frames.depth_m[0, 0, 0] = 1.0


class _FailingSource(ArrayFrameSource):
    def load(self, idx):
        if idx == 2:
            raise SceneError("frame file xyz.png: unreadable or corrupt image")
        return super().load(idx)


def test_failing_save_leaves_nothing(tmp_path):
    s = _scene(n=4)
    s.frames = _FailingSource(s.frames.color, s.frames.depth_m)
    with pytest.raises(SceneError, match="xyz.png"):
        save_scene(s, tmp_path / "scene")
    assert not (tmp_path / "scene").exists() and not (tmp_path / "scene.partial").exists()


def test_failing_overwrite_keeps_old_scene(tmp_path):
    dst = save_scene(_scene(seed=1), tmp_path / "scene")
    before = np.array(load_scene(dst).frames.color)
    bad = _scene(n=4)
    bad.frames = _FailingSource(bad.frames.color, bad.frames.depth_m)
    with pytest.raises(SceneError):
        save_scene(bad, dst, overwrite=True)
    np.testing.assert_array_equal(load_scene(dst).frames.color, before)
    with pytest.raises(FileExistsError):
        save_scene(_scene(), dst)


def test_version_and_format_checks(tmp_path):
    dst = save_scene(_scene(), tmp_path / "scene")
    hdr = json.loads((dst / "scene.json").read_text())
    hdr["version"] = FORMAT_VERSION + 1
    (dst / "scene.json").write_text(json.dumps(hdr))
    with pytest.raises(SceneError, match=f"version {FORMAT_VERSION + 1} is not supported"):
        load_scene(dst)
    hdr["version"], hdr["format"] = FORMAT_VERSION, "other"
    (dst / "scene.json").write_text(json.dumps(hdr))
    with pytest.raises(SceneError, match="unknown format"):
        load_scene(dst)
    (dst / "scene.json").write_text("{")
    with pytest.raises(SceneError, match="corrupt JSON"):
        load_scene(dst)
    with pytest.raises(SceneError, match="not a PreSim scene"):
        load_scene(tmp_path / "missing")
    (tmp_path / "half.partial").mkdir()
    with pytest.raises(SceneError, match="incomplete"):
        load_scene(tmp_path / "half")


def test_fuse_point_cloud_voxel_dedup():
    s = _scene(n=2)
    s.frames.depth_m[:] = 2.0
    s.T_world_cam[:] = np.eye(4)
    s.intrinsics[:] = [s.intrinsics[0]] * 2
    pc = fuse_point_cloud(s, voxel_m=0.01, stride=1)
    # both frames see the same plane from the same pose: the second adds nothing
    one = fuse_point_cloud(s.subset([0]), voxel_m=0.01, stride=1)
    assert len(pc) == len(one) and len(one) > 0
    np.testing.assert_allclose(pc.xyz[:, 2], 2.0, atol=1e-6)


def test_fuse_point_cloud_batches_keep_the_first_point_per_voxel():
    """Batched dedup (any batch size) keeps exactly the points frame-by-frame dedup keeps: per
    voxel the first one seen in frame order."""
    s = _scene(n=5)
    s.frames.depth_m[:] = 2.0
    s.T_world_cam[:] = [make_pose(np.eye(3), [0.003 * i, 0.0, 0.0]) for i in range(5)]
    ref = fuse_point_cloud(s, voxel_m=0.01, stride=1, batch_frames=1)
    for bf in (2, 16):
        got = fuse_point_cloud(s, voxel_m=0.01, stride=1, batch_frames=bf)
        ka, kb = np.lexsort(ref.xyz.T), np.lexsort(got.xyz.T)
        np.testing.assert_array_equal(ref.xyz[ka], got.xyz[kb])
        np.testing.assert_array_equal(ref.rgb[ka], got.rgb[kb])
    # Frames 1-4 overlap frame 0 shifted by < 1 voxel: each frame adds some new voxels, not all.
    first = fuse_point_cloud(s.subset([0]), voxel_m=0.01, stride=1)
    assert len(first) < len(ref) < 5 * len(first)


def test_damaged_scene_errors_name_the_file(tmp_path):
    dst = save_scene(_scene(), tmp_path / "s")
    data = (dst / "color.npy").read_bytes()
    (dst / "color.npy").write_bytes(data[: len(data) // 2])  # truncated copy
    with pytest.raises(SceneError, match=r"color\.npy: unreadable array"):
        load_scene(dst)
    (dst / "color.npy").write_bytes(data)
    hdr = json.loads((dst / "scene.json").read_text())
    del hdr["frames"]
    (dst / "scene.json").write_text(json.dumps(hdr))
    with pytest.raises(SceneError, match=r"scene\.json: missing or malformed field \(KeyError: 'frames'\)"):
        load_scene(dst)
