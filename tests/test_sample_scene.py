"""The built-in sample scene: determinism, exact ground truth, corruption model, objects, CLI."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest

os.environ.setdefault("PRESIM_NO_PROGRESS", "1")

from presim.capture.procedural import NoiseField, box_mesh, cylinder_mesh, ellipsoid_mesh, rock_mesh  # noqa: E402
from presim.capture.reprojection import reprojection_mae  # noqa: E402
from presim.capture.sample_scene import (  # noqa: E402
    SampleSceneConfig, build_sample_scene, clean_scene, corrupt_depth, load_sample_ground_truth,
    render_ground_truth, render_object_silhouettes,
)
from presim.capture.store import load_scene, model_abspath  # noqa: E402
from presim.geometry import (  # noqa: E402
    Intrinsics, compose, invert, look_at, project, transform_points, unproject_depth,
)

SMALL = SampleSceneConfig(width=160, height=120, num_frames=24)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return build_sample_scene(tmp_path_factory.mktemp("sample") / "s0", seed=0, config=SMALL)


def _arrays(dst):
    return {name: np.load(dst / name) for name in ("color.npy", "depth.npy", "ground_truth/depth_clean.npy",
                                                   "ground_truth/object_id.npy")}


def test_deterministic_for_a_seed(small, tmp_path):
    again = build_sample_scene(tmp_path / "again", seed=0, config=SMALL)
    a, b = _arrays(small), _arrays(again)
    for name in a:
        assert a[name].tobytes() == b[name].tobytes(), name
    assert (small / "ground_truth" / "room.ply").read_bytes() == (again / "ground_truth" / "room.ply").read_bytes()
    other = _arrays(build_sample_scene(tmp_path / "other", seed=1, config=SMALL))
    for name in a:
        assert a[name].tobytes() != other[name].tobytes(), name


def test_saved_scene_layout(small):
    scene = load_scene(small)
    assert len(scene) == SMALL.num_frames and (scene.width, scene.height) == (160, 120)
    assert scene.floor is not None and scene.floor.normal == (0.0, 0.0, 1.0) and scene.floor.offset == 0.0
    np.testing.assert_array_equal(scene.gravity_world, [0, 0, -1])
    assert [o.obj_id for o in scene.objects] == [1, 2, 3, 4, 5]
    assert len({o.name for o in scene.objects}) == 5
    assert not small.with_name(small.name + ".partial").exists()
    gt = load_sample_ground_truth(small)
    assert gt.depth_clean_m.shape == (24, 120, 160) and gt.depth_clean_m.dtype == np.float32
    kinds = {p.kind for p in gt.parts}
    assert {"floor", "wall", "ceiling", "furniture", "obstacle", "object"} <= kinds
    # Every camera is inside the room at hand-held height, steps of a few cm to ~15 cm at 60 frames.
    c = scene.camera_centres
    assert np.all(np.abs(c[:, 0]) < 2.3) and np.all(np.abs(c[:, 1]) < 1.8)
    assert np.all((c[:, 2] > 1.0) & (c[:, 2] < 1.5))


def test_trajectory_steps_default_density():
    from presim.capture.sample_scene import capture_trajectory
    from presim.capture.sample_scene.render import scene_raycaster

    cfg = SampleSceneConfig()
    T = capture_trajectory(scene_raycaster(0, dataclasses.replace(SMALL, num_frames=60)).layout, cfg.num_frames, 0)
    step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    assert 0.03 < step.min() and step.max() < 0.16


def _backward_color_error(scene, target_idx, source_idx, use_poses=True):
    """Per-pixel color error (gray levels) of target pixels looked up in the source through the
    target's depth and both poses, where the source sees the same surface point (its depth agrees
    within 1 %). Returns (errors, fraction of target pixels compared)."""
    ft, fs = scene.frame(target_idx), scene.frame(source_idx)
    T_src_tgt = compose(invert(fs.T_world_cam), ft.T_world_cam) if use_poses else np.eye(4)
    pts, mask = unproject_depth(ft.K, ft.depth_m, T_src_tgt)
    uv, z = project(fs.K, pts)
    ok = np.isfinite(uv).all(1)
    u = np.rint(np.where(ok, uv[:, 0], -1)).astype(int)
    v = np.rint(np.where(ok, uv[:, 1], -1)).astype(int)
    ok &= (u >= 0) & (u < fs.K.width) & (v >= 0) & (v < fs.K.height)
    ok[ok] &= np.abs(fs.depth_m[v[ok], u[ok]] - z[ok]) < 0.01 * z[ok]
    c_t = ft.color[mask][ok].astype(np.float32)
    c_s = fs.color[v[ok], u[ok]].astype(np.float32)
    return np.abs(c_t - c_s).mean(1), ok.sum() / mask.size


def test_clean_depth_explains_colors(small):
    scene = clean_scene(small)
    means, means0 = [], []
    for i in (0, 6, 12, 18, 22):
        err, frac = _backward_color_error(scene, i + 1, i)
        err0, _ = _backward_color_error(scene, i + 1, i, use_poses=False)
        assert frac > 0.3
        # Point-sampled textures at 160x120: most pixels match to a few levels, texture edges
        # (book spines, mortar) smaller than a pixel footprint differ more.
        assert np.median(err) <= 2.0, (i, np.median(err))
        means.append(err.mean())
        means0.append(err0.mean() if len(err0) else np.nan)
        mae, cov = reprojection_mae(scene, i + 1, i)
        mae0, _ = reprojection_mae(scene, i + 1, i, use_poses=False)
        assert cov > 0.2 and mae < 0.35 * mae0, (i, mae, mae0)
    assert np.mean(means) < 8.0, means
    # With a wrong pose convention (world-to-camera) nothing lines up.
    err_bad, _ = _backward_color_error(dataclasses.replace(scene, T_world_cam=invert(scene.T_world_cam)), 7, 6)
    assert len(err_bad) == 0 or err_bad.mean() > 3 * np.mean(means)


def test_render_ground_truth_equals_capture(small):
    scene = clean_scene(small)
    gt = load_sample_ground_truth(small)
    for i in (0, 11, 23):
        f = scene.frame(i)
        color, depth, obj = render_ground_truth(small, f.T_world_cam, f.K)
        assert color.dtype == np.uint8 and depth.dtype == np.float32 and obj.dtype == np.int32
        np.testing.assert_array_equal(color, f.color)
        np.testing.assert_array_equal(depth, f.depth_m)
        np.testing.assert_array_equal(obj, gt.object_id[i])


def test_object_masks_and_table_poses(small):
    import open3d as o3d

    scene = load_scene(small)
    gt = load_sample_ground_truth(small)
    K = Intrinsics.from_fov(160, 120, 60.0)
    for o in scene.objects:
        mesh = o3d.io.read_triangle_mesh(str(model_abspath(scene, o)))
        v = np.asarray(mesh.vertices)
        assert len(mesh.triangles) > 0 and mesh.has_vertex_colors()
        size = v.max(0) - v.min(0)
        assert 0.05 <= size.max() <= 0.25, (o.name, size)
        bottom = transform_points(o.T_world_obj, v)[:, 2].min()
        assert abs(bottom - gt.table_top_z_m) < 1e-3, (o.name, bottom)
        # A camera 0.5 m away, looking at the object's centre, sees it.
        centre = transform_points(o.T_world_obj, (v.min(0) + v.max(0)) / 2)
        eye = centre + np.array([0.35, 0.0, 0.35])
        _, depth, obj = render_ground_truth(small, look_at(eye, centre), K)
        assert (obj == o.obj_id).sum() > 50, o.name
        assert np.all(depth[obj == o.obj_id] > 0)
    # Full silhouettes (objects alone) contain the visible masks and agree on depth there.
    f = load_scene(small).frame(23)
    _, depth, obj = render_ground_truth(small, f.T_world_cam, f.K)
    ids, masks, depths = render_object_silhouettes(small, f.T_world_cam, f.K)
    assert list(ids) == [1, 2, 3, 4, 5]
    for k, oid in enumerate(ids):
        vis = obj == oid
        assert np.all(masks[k][vis]) and masks[k].sum() >= vis.sum()
        np.testing.assert_allclose(depths[k][vis], depth[vis], atol=1e-6)
    # Objects seen in the capture have non-empty masks in the stored ground truth too.
    seen = set(np.unique(np.asarray(gt.object_id))) - {0}
    assert seen == {1, 2, 3, 4, 5}


def test_corruption_model(small):
    scene = load_scene(small)
    gt = load_sample_ground_truth(small)
    raw = np.asarray(scene.frames.depth_m)
    clean = np.asarray(gt.depth_clean_m)
    du, dv = SMALL.shift_px
    # Undo the registration shift to compare the same surface points.
    aligned = raw[:, dv:, du:]
    ref = clean[:, :-dv, :-du]
    ok = (aligned > 0) & (ref > 0)
    missing = 1.0 - (raw > 0).sum() / (clean > 0).sum()
    assert 0.02 < missing < 0.4, missing
    assert raw.max() <= SMALL.max_range_m and raw[raw > 0].min() >= SMALL.min_range_m
    err = (aligned - ref)[ok]
    z = ref[ok]
    near = np.abs(err[(z > 0.5) & (z < 1.5)])
    far = np.abs(err[(z > 2.5) & (z < 4.0)])
    med_near, med_far = np.median(near), np.median(far)
    assert med_far > 2.5 * med_near, (med_near, med_far)
    # The misregistration: shifting back by shift_px fits the clean depth best.
    def mean_abs(sh_u, sh_v):
        a = raw[:, 4 + sh_v:116 + sh_v, 4 + sh_u:156 + sh_u]
        b = clean[:, 4:116, 4:156]
        m = (a > 0) & (b > 0)
        return np.mean(np.minimum(np.abs(a - b)[m], 0.5))
    errs = {(u, v): mean_abs(u, v) for u in range(-3, 4) for v in range(-3, 4)}
    assert min(errs, key=errs.get) == (du, dv)


def test_corrupt_depth_rules():
    cfg = SampleSceneConfig(speckle_dropout=0.0, edge_shadow_px=0, edge_dilate_px=0, shift_px=(0, 0))
    h, w = 60, 80
    depth = np.full((h, w), 2.0, np.float32)
    depth[:, :10] = 0.2          # too close
    depth[:, 10:20] = 5.0        # too far
    lum = np.full((h, w), 0.5, np.float32)
    lum[:, 20:30] = 0.01         # dark
    cos = np.ones((h, w), np.float32)
    cos[:, 30:40] = np.cos(np.radians(88.0))  # grazing
    out = corrupt_depth(depth, lum, cos, cfg, np.random.default_rng(0))
    assert np.all(out[:, :20] == 0)
    assert (out[:, 20:30] == 0).mean() > 0.8
    assert np.all(out[:, 30:40] == 0)
    good = out[:, 40:]
    assert np.all(good > 0)
    sigma = cfg.noise_sigma0_m + cfg.noise_k_per_m * 4.0
    assert abs(np.std(good - 2.0) / sigma - 1.0) < 0.1


def test_noise_backends_match():
    nf = NoiseField(3)
    p = np.random.default_rng(0).uniform(-3, 3, (2000, 3))
    np.testing.assert_allclose(nf.fbm(p, 0.2, 4, 1.5), nf.fbm(p, 0.2, 4, 1.5, backend="reference"), atol=1e-12)


def test_meshes_are_closed_and_outward():
    rng = np.random.default_rng(0)
    for m in (box_mesh([0, 0, 0], [1, 2, 3]), cylinder_mesh(0.1, 0.2), ellipsoid_mesh([0.1, 0.1, 0.08]),
              rock_mesh(0.06, rng)):
        v, f = m.vertices, m.triangles
        # Divergence theorem: signed volume is positive for outward-wound closed meshes.
        vol = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6
        assert vol > 0


def test_bad_input(tmp_path, small):
    with pytest.raises(FileExistsError):
        build_sample_scene(small, seed=0, config=SMALL)
    with pytest.raises(ValueError, match="num_objects"):
        build_sample_scene(tmp_path / "x", config=dataclasses.replace(SMALL, num_objects=7))
    assert not (tmp_path / "x").exists() and not (tmp_path / "x.partial").exists()
    with pytest.raises(FileNotFoundError, match="sample.json"):
        render_ground_truth(tmp_path, np.eye(4), Intrinsics.from_fov(16, 16, 60))
    with pytest.raises(ValueError, match="T_world_cam"):
        render_ground_truth(small, np.diag([2.0, 1.0, 1.0, 1.0]), Intrinsics.from_fov(16, 16, 60))


def test_cli(tmp_path):
    from presim.cli import main

    dst = tmp_path / "cli"
    assert main(["sample-scene", str(dst), "--seed", "2", "--frames", "3", "--width", "64", "--height", "48",
                 "--objects", "3"]) == 0
    scene = load_scene(dst)
    assert len(scene) == 3 and scene.width == 64 and len(scene.objects) == 3
    assert main(["sample-scene", str(dst), "--frames", "3", "--width", "64", "--height", "48"]) == 1
    assert main(["sample-scene", str(dst), "--frames", "3", "--width", "64", "--height", "48", "--overwrite"]) == 0


def test_variants_without_door_and_ceiling(tmp_path):
    cfg = SampleSceneConfig(width=48, height=36, num_frames=3, door=False, ceiling=False, num_objects=4,
                            shadows=False)
    dst = build_sample_scene(tmp_path / "v", seed=5, config=cfg)
    gt = load_sample_ground_truth(dst)
    names = {p.name for p in gt.parts}
    assert "wall_north" in names and "ceiling" not in names and "corridor_end" not in names
    assert len(load_scene(dst).objects) == 4
    # Straight up there is nothing without a ceiling.
    _, depth, _ = render_ground_truth(dst, look_at([0, 0, 1.2], [0.01, 0, 3.0]), Intrinsics.from_fov(8, 8, 30))
    assert np.all(depth == 0)
