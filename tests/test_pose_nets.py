"""Pose networks (presim/pose/nets): loss known answers, graph layers' shapes and permutation
equivariance, the dataset on a tiny rendered BOP folder, a one-object overfit, training/resume/NaN,
pose-predict -> pose-eval round trip, and one-line errors for bad datasets."""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from presim.pose.nets.data import PoseDataConfig, PoseInstanceDataset
from presim.pose.nets.loss import LossConfig, point_distances, pose_loss, quat_to_R, symmetric_add
from presim.pose.nets.models import ARCHS, EdgeConv, GraphAttention, ModelConfig, PoseNet, best_pose, knn
from presim.testing.boxes import box_mesh, box_surface_points

W, H = 160, 120
K = np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]])
BOX_MM = np.array([80.0, 50.0, 30.0])
TINY = dict(cnn_width=8, emb_dim=16, geo_dims=(16, 16, 16), global_dim=32, fuse_dim=16, head_dims=(32,))


def _box_mesh(size):
    return box_mesh(size)


def _box_surface_pts(size, n=7):
    return box_surface_points(size, n)


def _write_ply(path: Path, v, f):
    lines = ["ply", "format ascii 1.0", f"element vertex {len(v)}", "property float x", "property float y",
             "property float z", f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    lines += [f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f}" for p in v] + ["3 " + " ".join(map(str, t)) for t in f]
    path.write_text("\n".join(lines) + "\n")


def _rot(*e):
    return Rotation.from_euler("xyz", e, degrees=True).as_matrix()


def make_bop(root: Path, n_images: int = 4, split: str = "test", seed: int = 0) -> Path:
    """Two boxes (obj 1 plain, obj 2 declared 180-degree symmetric) rendered at known poses, 160x120,
    depth from the true meshes; model PLYs hold the surface grid (vertices) and the box faces."""
    from presim.io_utils import write_png
    from presim.pose.metrics import MeshDepthRenderer

    v, f = _box_mesh(BOX_MM)
    (root / "models").mkdir(parents=True, exist_ok=True)
    sym = np.eye(4)
    sym[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    info = {}
    for obj_id in (1, 2):
        # surface points as extra (unreferenced) vertices so the loss gets points on every face
        pts = np.vstack([v, _box_surface_pts(BOX_MM)])
        _write_ply(root / "models" / f"obj_{obj_id:06d}.ply", pts, f)
        info[str(obj_id)] = {"diameter": float(np.linalg.norm(BOX_MM)), "min_x": -40, "min_y": -25, "min_z": -15,
                             "size_x": 80, "size_y": 50, "size_z": 30}
    info["2"]["symmetries_discrete"] = [sym.reshape(-1).tolist()]
    (root / "models" / "models_info.json").write_text(json.dumps(info))
    (root / "camera.json").write_text(json.dumps({"fx": 150.0, "fy": 150.0, "cx": 79.5, "cy": 59.5,
                                                  "width": W, "height": H, "depth_scale": 0.1}))
    sd = root / split / "000001"
    for d in ("depth", "rgb", "mask_visib"):
        (sd / d).mkdir(parents=True, exist_ok=True)
    rend = MeshDepthRenderer(v * 1e-3, f)
    rng = np.random.default_rng(seed)
    gt, cam, ginfo = {}, {}, {}
    for im_id in range(n_images):
        poses = [(1, _rot(*rng.uniform(-40, 40, 3)), np.array([-0.06, 0.0, 0.6]) + rng.uniform(-0.01, 0.01, 3)),
                 (2, _rot(*rng.uniform(-40, 40, 3)), np.array([0.07, 0.01, 0.65]) + rng.uniform(-0.01, 0.01, 3))]
        depths = [rend(R, t, K, W, H) for _, R, t in poses]
        depth = np.zeros((H, W), np.float32)
        for d in depths:
            depth = np.where((d > 0) & ((depth == 0) | (d < depth)), d, depth)
        rgb = np.full((H, W, 3), 40, np.uint8)
        gt[str(im_id)], ginfo[str(im_id)] = [], []
        for k, ((obj_id, R, t), d) in enumerate(zip(poses, depths)):
            m = (d > 0) & (np.abs(d - depth) < 1e-6)
            shade = np.clip((0.7 - depth) * 400 + 128, 0, 255)
            rgb[m] = np.stack([shade, 255 - shade, np.full_like(shade, 80 * obj_id)], -1)[m].astype(np.uint8)
            write_png(sd / "mask_visib" / f"{im_id:06d}_{k:06d}.png", (m * 255).astype(np.uint8))
            gt[str(im_id)].append({"cam_R_m2c": R.reshape(-1).tolist(), "cam_t_m2c": (t * 1000).tolist(), "obj_id": obj_id})
            n = int(m.sum())
            ginfo[str(im_id)].append({"bbox_obj": [0, 0, 1, 1], "bbox_visib": [0, 0, 1, 1], "px_count_all": int((d > 0).sum()),
                                      "px_count_valid": n, "px_count_visib": n,
                                      "visib_fract": n / max(int((d > 0).sum()), 1)})
        write_png(sd / "rgb" / f"{im_id:06d}.png", rgb)
        write_png(sd / "depth" / f"{im_id:06d}.png", np.round(depth * 1000 / 0.1).astype(np.uint16))
        cam[str(im_id)] = {"cam_K": K.reshape(-1).tolist(), "depth_scale": 0.1}
    (sd / "scene_gt.json").write_text(json.dumps(gt))
    (sd / "scene_camera.json").write_text(json.dumps(cam))
    (sd / "scene_gt_info.json").write_text(json.dumps(ginfo))
    return root


@pytest.fixture(scope="module")
def bop(tmp_path_factory) -> Path:
    return make_bop(tmp_path_factory.mktemp("posenets") / "bop")


DATA_CFG = PoseDataConfig(split="test", n_points=64, n_model_points=100, crop_px=32, min_points=16)


# ---- loss -------------------------------------------------------------------------------------

def test_quat_to_R_matches_scipy():
    q = torch.tensor([[0.9, 0.1, -0.3, 0.2], [1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    R = quat_to_R(q).numpy()
    qn = q.numpy() / np.linalg.norm(q.numpy(), axis=1, keepdims=True)
    ref = Rotation.from_quat(qn[:, [1, 2, 3, 0]]).as_matrix()  # scipy is (x, y, z, w)
    np.testing.assert_allclose(R, ref, atol=1e-12)


def _batch(R, t, pts):
    m = torch.as_tensor(pts, dtype=torch.float64)[None]
    target = m @ torch.as_tensor(R).T + torch.as_tensor(t)
    return m, target


def test_loss_zero_at_true_pose_and_add_at_known_offset():
    pts = _box_surface_pts(BOX_MM) * 1e-3
    R, t = _rot(10, 20, 30), np.array([0.0, 0.0, 0.6])
    m, target = _batch(R, t, pts)
    Rp = torch.as_tensor(R)[None, None].repeat(1, 3, 1, 1)
    tp = torch.as_tensor(t)[None, None].repeat(1, 3, 1)
    tp[0, 1] += torch.tensor([0.03, 0.0, 0.04], dtype=torch.float64)  # point 1: 5 cm off -> ADD = 0.05 exactly
    conf = torch.ones(1, 3, dtype=torch.float64)
    out = pose_loss(Rp, tp, conf, m, target, torch.tensor([False]))
    np.testing.assert_allclose(out.dist_m.numpy(), [[0.0, 0.05, 0.0]], atol=1e-12)
    assert out.loss.item() == pytest.approx(0.05 / 3, abs=1e-12)  # c = 1: log term vanishes
    # all at the true pose with c = 1: exactly zero
    assert pose_loss(Rp[:, :1], torch.as_tensor(t)[None, None], conf[:, :1], m, target,
                     torch.tensor([False])).loss.item() == pytest.approx(0.0, abs=1e-12)
    # confidence 0.5: D*c - w*log c
    out = pose_loss(Rp[:, 1:2], tp[:, 1:2], torch.full((1, 1), 0.5, dtype=torch.float64), m, target, torch.tensor([False]))
    assert out.loss.item() == pytest.approx(0.05 * 0.5 - 0.015 * math.log(0.5), abs=1e-12)


def test_add_s_of_symmetric_flip_is_zero_and_add_is_hand_value():
    pts = _box_surface_pts(BOX_MM) * 1e-3   # symmetric under 180 deg about z
    R, t = _rot(-20, 10, 0), np.array([0.05, 0.0, 0.7])
    m, target = _batch(R, t, pts)
    R_flip = torch.as_tensor(R @ np.diag([-1.0, -1.0, 1.0]))[None, None]
    tt = torch.as_tensor(t)[None, None]
    add_hand = float(np.mean(2 * np.hypot(pts[:, 0], pts[:, 1])))  # |R_z(pi) x - x| = 2 hypot(x, y)
    d_add = point_distances(R_flip, tt, m, target, torch.tensor([False]))
    d_adds = point_distances(R_flip, tt, m, target, torch.tensor([True]))
    assert d_add.item() == pytest.approx(add_hand, rel=1e-9)
    assert d_adds.item() == pytest.approx(0.0, abs=1e-7)  # cdist uses |a|^2+|b|^2-2ab: ~1e-9 m rounding


def test_symmetric_add_accepts_listed_symmetries_only():
    """Box declared symmetric under 180 deg about z: that flip costs 0, a 180 deg flip about x (not
    listed, though ADD-S cannot tell it from the truth) costs its hand-computed ADD."""
    pts = _box_surface_pts(BOX_MM) * 1e-3
    R, t = _rot(-20, 10, 0), np.array([0.05, 0.0, 0.7])
    m, target = _batch(R, t, pts)
    Tz = np.diag([-1.0, -1.0, 1.0])
    sym_targets = torch.stack([target[0], torch.as_tensor(pts @ (R @ Tz).T + t)])[None]   # (1, 2, M, 3)
    R_z = torch.as_tensor(R @ Tz)[None, None]
    R_x = torch.as_tensor(R @ np.diag([1.0, -1.0, -1.0]))[None, None]
    tt = torch.as_tensor(t)[None, None]
    assert symmetric_add(R_z, tt, m, sym_targets).item() == pytest.approx(0.0, abs=1e-12)
    add_x = float(np.mean(2 * np.hypot(pts[:, 1], pts[:, 2])))  # |R_x(pi) x - x| = 2 hypot(y, z)
    assert symmetric_add(R_x, tt, m, sym_targets).item() == pytest.approx(add_x, rel=1e-9)
    assert point_distances(R_x, tt, m, target, torch.tensor([True])).item() == pytest.approx(0.0, abs=1e-7)
    # one copy (asymmetric object) = plain ADD; the loss uses it with symmetry="transforms"
    assert symmetric_add(R_z, tt, m, target[:, None]).item() == pytest.approx(
        point_distances(R_z, tt, m, target, torch.tensor([False])).item(), rel=1e-12)
    conf = torch.ones(1, 1, dtype=torch.float64)
    lo = pose_loss(R_x, tt, conf, m, target, torch.tensor([True]), LossConfig(), sym_targets=sym_targets)
    assert lo.loss.item() == pytest.approx(add_x, rel=1e-9)
    lo = pose_loss(R_x, tt, conf, m, target, torch.tensor([True]), LossConfig(symmetry="adds"), sym_targets=sym_targets)
    assert lo.loss.item() == pytest.approx(0.0, abs=1e-7)


def test_lr_schedule_warmup_and_cosine_known_values():
    from presim.pose.nets.train import QUICK_LR, QUICK_SEG_LR, QUICK_STEPS, TrainConfig

    cfg = TrainConfig(lr=1e-3, warmup_frac=0.1)
    assert [cfg.lr_at(s, 100) for s in (0, 4, 9)] == pytest.approx([1e-4, 5e-4, 1e-3])
    assert cfg.lr_at(10, 100) == pytest.approx(1e-3)
    assert cfg.lr_at(55, 100) == pytest.approx(0.5e-3)           # half-way through the decay: cos(pi/2)
    assert cfg.lr_at(100, 100) == pytest.approx(0.0, abs=1e-15)
    assert TrainConfig(lr_schedule="constant").lr_at(7, 100) == 1e-3
    assert TrainConfig().epochs == 0 and TrainConfig().total_steps(85) == QUICK_STEPS
    assert TrainConfig(epochs=3).total_steps(85) == 255
    # lr left unset: the quick recipe's rate for the model, recorded as a number
    assert TrainConfig().lr == QUICK_LR and TrainConfig(model="segmentation").lr == QUICK_SEG_LR
    assert TrainConfig(model="segmentation", lr=5e-4).lr == 5e-4
    with pytest.raises(ValueError, match="lr"):
        TrainConfig(lr=float("nan"))
    with pytest.raises(ValueError, match="unknown schedule"):
        TrainConfig(lr_schedule="step").lr_at(0, 10)


# ---- layers -----------------------------------------------------------------------------------

def test_knn_self_first_and_edgeconv_gat_shapes_equivariance():
    g = torch.Generator().manual_seed(0)
    B, N, k = 2, 40, 10
    pts = torch.rand(B, N, 3, generator=g)
    idx = knn(pts, k)
    assert idx.shape == (B, N, k)
    assert torch.equal(idx[..., 0], torch.arange(N).expand(B, N))
    feat = torch.rand(B, 5, N, generator=g)
    ec, gat = EdgeConv(5, 12), GraphAttention(5, 12, heads=2)
    y = ec(feat, idx)
    z, alpha = gat(feat, idx, return_attention=True)
    assert y.shape == (B, 12, N) and z.shape == (B, 12, N) and alpha.shape == (B, 2, N, k)
    torch.testing.assert_close(alpha.sum(-1), torch.ones(B, 2, N))
    perm = torch.randperm(N, generator=g)
    idx_p = knn(pts[:, perm], k)
    torch.testing.assert_close(ec(feat[..., perm], idx_p), y[..., perm], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(gat(feat[..., perm], idx_p), z[..., perm], rtol=1e-5, atol=1e-6)


def test_edgeconv_fast_form_equals_the_edge_tensor_form():
    torch.manual_seed(0)
    x, pts = torch.randn(3, 7, 30), torch.rand(3, 30, 3)
    ec = EdgeConv(7, 16)
    idx = knn(pts, 10)
    torch.testing.assert_close(ec(x, idx), ec.forward_reference(x, idx), rtol=1e-5, atol=1e-5)
    x.requires_grad_(True)
    g1 = torch.autograd.grad(ec(x, idx).sum(), x)[0]
    g2 = torch.autograd.grad(ec.forward_reference(x, idx).sum(), x)[0]
    torch.testing.assert_close(g1, g2, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("arch", ARCHS)
def test_posenet_per_point_outputs_are_permutation_equivariant(arch):
    torch.manual_seed(0)
    net = PoseNet(ModelConfig(arch=arch, n_objects=3, **TINY)).eval()
    B, N, S = 2, 50, 32
    rgb = torch.randn(B, 3, S, S)
    pts = torch.randn(B, N, 3) * 0.03 + torch.tensor([0.0, 0.0, 0.8])
    ch = torch.randint(0, S * S, (B, N))
    oi = torch.tensor([2, 0])
    perm = torch.randperm(N)
    with torch.no_grad():
        a, b = net(rgb, pts, ch, oi), net(rgb, pts[:, perm], ch[:, perm], oi)
    assert a.R.shape == (B, N, 3, 3) and a.t.shape == (B, N, 3) and a.conf.shape == (B, N)
    torch.testing.assert_close(b.R, a.R[:, perm], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(b.t, a.t[:, perm], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(b.conf, a.conf[:, perm], rtol=1e-4, atol=1e-5)
    # rotations are rotations
    RtR = a.R.transpose(-1, -2) @ a.R
    torch.testing.assert_close(RtR, torch.eye(3).expand_as(RtR), atol=1e-5, rtol=0)
    # the refiner (global features only) is invariant
    R0, t0, _ = best_pose(a)
    with torch.no_grad():
        r1 = net.refine(pts, a.emb, oi, R0, t0)
        r2 = net.refine(pts[:, perm], a.emb[..., perm], oi, R0, t0)
    torch.testing.assert_close(r1[0], r2[0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(r1[1], r2[1], rtol=1e-4, atol=1e-5)


def test_unknown_arch_is_an_error():
    with pytest.raises(ValueError, match="unknown pose network"):
        PoseNet(ModelConfig(arch="posecnn"))


# ---- data -------------------------------------------------------------------------------------

def test_dataset_points_lie_on_the_model_at_the_true_pose(bop):
    ds = PoseInstanceDataset(bop, DATA_CFG)
    assert len(ds) == 8 and ds.objects.obj_ids == (1, 2)
    assert ds.objects.symmetric == {1: False, 2: True}
    for i in range(len(ds)):
        it = ds[i]
        assert it["rgb"].shape == (3, 32, 32) and it["points"].shape == (64, 3) and it["choose"].shape == (64,)
        assert int(it["choose"].max()) < 32 * 32
        R, t = it["R_gt"].double().numpy(), it["t_gt"].double().numpy()
        p_obj = (it["points"].double().numpy() - t) @ R  # camera -> model frame
        # depth PNG quantisation 0.01 mm and float32: points on the box surface within 0.5 mm
        assert np.all(np.abs(p_obj) <= BOX_MM / 2e3 + 5e-4)
        assert np.max(np.abs(p_obj) / (BOX_MM / 2e3), axis=1).min() > 0.95
        np.testing.assert_allclose(it["target"].numpy(), it["model_points"].numpy() @ R.T + t, atol=1e-6)


def test_cached_instances_equal_uncached_and_symmetry_targets(bop):
    """The cache (prepared crop + depth pixels) gives the same items as reading the files each time;
    sym_targets hold the true pose and its listed symmetric copy (object 2: 180 deg about z)."""
    cfg = replace(DATA_CFG, augment=True)
    a, b = PoseInstanceDataset(bop, replace(cfg, cache=False)), PoseInstanceDataset(bop, cfg)
    b.precompute()
    assert len(b._cache) == len(b)
    for i in range(len(a)):
        x, y = a[i], b[i]
        assert set(x) == set(y)
        for k in x:
            assert torch.equal(x[k], y[k]), k
        st, m = y["sym_targets"].double().numpy(), y["model_points"].double().numpy()
        R, t = y["R_gt"].double().numpy(), y["t_gt"].double().numpy()
        np.testing.assert_allclose(st[0], y["target"].numpy(), atol=1e-6)
        second = m @ (R @ np.diag([-1.0, -1.0, 1.0])).T + t if int(y["obj_id"]) == 2 else m @ R.T + t
        np.testing.assert_allclose(st[1], second, atol=1e-6)   # object 1: padded with the identity


def test_augmentation_changes_colour_and_depth_but_not_the_target(bop):
    a = PoseInstanceDataset(bop, DATA_CFG)[0]
    b = PoseInstanceDataset(bop, replace(DATA_CFG, augment=True, depth_noise_m=0.002))[0]
    assert torch.equal(a["choose"], b["choose"])  # same draw of pixels for the same (seed, epoch, index)
    dz = (b["points"][:, 2] - a["points"][:, 2]).numpy()
    assert 0.0005 < dz.std() < 0.004
    assert not torch.allclose(a["rgb"], b["rgb"])
    assert torch.equal(a["target"], b["target"])


def test_bad_datasets_give_one_line_errors(bop, tmp_path, capsys):
    from presim.cli import main

    # no depth
    nodepth = tmp_path / "nodepth"
    shutil.copytree(bop, nodepth)
    shutil.rmtree(nodepth / "test" / "000001" / "depth")
    with pytest.raises(ValueError, match="no depth images"):
        PoseInstanceDataset(nodepth, DATA_CFG)
    # object without a model
    nomodel = tmp_path / "nomodel"
    shutil.copytree(bop, nomodel)
    (nomodel / "models" / "obj_000002.ply").unlink()
    with pytest.raises(FileNotFoundError, match="obj_000002.ply"):
        PoseInstanceDataset(nomodel, DATA_CFG)
    # empty split
    empty = tmp_path / "empty"
    shutil.copytree(bop / "models", empty / "models")
    (empty / "test").mkdir()
    with pytest.raises(ValueError, match="no scene folders"):
        PoseInstanceDataset(empty, DATA_CFG)
    for ds, msg in ((nodepth, "no depth images"), (nomodel, "obj_000002.ply"), (empty, "no scene folders")):
        capsys.readouterr()
        assert main(["pose-train", "--dataset", str(ds), "--split", "test", "--model", "cgaf",
                     "--out", str(tmp_path / "run")]) == 1
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and msg in lines[0] and lines[0].startswith("presim pose-train: error:")
    assert not (tmp_path / "run").exists()  # nothing that looks like a run is left
    # a refiner phase as long as the whole run
    capsys.readouterr()
    assert main(["pose-train", "--dataset", str(bop), "--split", "test", "--model", "cgaf", "--out",
                 str(tmp_path / "run"), "--steps", "3", "--refine-steps", "3"]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "--refine-steps: 3 is not below the run's 3 optimiser steps" in lines[0]
    # a learning rate that is not a positive number
    for bad in ("0", "-1", "nan"):
        assert main(["pose-train", "--dataset", str(bop), "--split", "test", "--model", "cgaf", "--out",
                     str(tmp_path / "run"), "--lr", bad]) == 1
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and "--lr: must be a positive finite number" in lines[0]
    assert not (tmp_path / "run").exists()


# ---- training ---------------------------------------------------------------------------------

def _tiny_train_cfg(**kw):
    from presim.pose.nets.train import TrainConfig
    return replace(TrainConfig(model="densefusion", batch_size=4, lr=2e-3, data=replace(DATA_CFG, augment=False)), **kw)


def test_refiner_phase_trains_the_refiner_alone(bop):
    """refine=True: the estimator runs without gradient, only the refiner's parameters get one."""
    from presim.pose.nets import train as tr

    torch.manual_seed(0)
    cfg = _tiny_train_cfg(model="cgaf")
    ds = PoseInstanceDataset(bop, cfg.data)
    batch = {k: torch.stack([ds[i][k] for i in range(2)]) for k in ds[0]}
    net = PoseNet(ModelConfig(arch="cgaf", n_objects=2, **TINY))
    loss, st = tr._pose_step(net, batch, cfg, refine=True)
    loss.backward()
    ref = {n for n, _ in net.named_parameters() if n.startswith("refiner.")}
    assert ref and all(p.grad is not None for n, p in net.named_parameters() if n in ref)
    assert all(p.grad is None for n, p in net.named_parameters() if n not in ref)
    assert st["add_refined_m"].shape == (2,)


@pytest.mark.slow
def test_one_object_overfit_reaches_1cm(bop, monkeypatch):
    """One instance, tiny network: the most confident pose reaches ADD < 1 cm within 300 steps."""
    from presim.pose.nets import train as tr

    monkeypatch.setattr(tr.TrainConfig, "model_config",
                        lambda self, n: ModelConfig(arch=self.model, n_objects=n, **TINY))
    torch.manual_seed(0)
    cfg = _tiny_train_cfg(model="cgaf")
    ds = PoseInstanceDataset(bop, cfg.data)
    batch = {k: v[None] for k, v in ds[0].items()}
    net = PoseNet(cfg.model_config(2))
    opt = torch.optim.Adam(net.parameters(), lr=2e-3)
    best = 1.0
    for step in range(300):
        loss, st = tr._pose_step(net, batch, cfg, refine=False)
        opt.zero_grad()
        loss.backward()
        opt.step()
        best = float(st["add_m"][0])
        if best < 0.01:
            break
    assert best < 0.01, f"ADD after {step + 1} steps: {best:.4f} m"


@pytest.mark.slow
def test_train_resume_metrics_and_nan_stop(bop, tmp_path, monkeypatch):
    from presim.pose.nets import train as tr

    monkeypatch.setattr(tr.TrainConfig, "model_config",
                        lambda self, n: ModelConfig(arch=self.model, n_objects=n, **TINY))
    run = tmp_path / "run"
    r1 = tr.train(bop, run, _tiny_train_cfg(epochs=1), show_progress=False)
    assert r1.epochs_done == 1 and r1.resumed_from == 0
    r2 = tr.train(bop, run, _tiny_train_cfg(epochs=2), show_progress=False)
    assert r2.resumed_from == 1 and [r["epoch"] for r in r2.rows] == [1, 2]
    lines = (run / "metrics.csv").read_text().strip().splitlines()
    assert lines[0].startswith("epoch,step,loss,add_m") and len(lines) == 3
    assert (run / "learning_curve.png").stat().st_size > 1000
    ck = tr.load_checkpoint(run / tr.CHECKPOINT)
    assert ck["epoch"] == 2
    with pytest.raises(ValueError, match="different settings"):
        tr.train(bop, run, _tiny_train_cfg(epochs=3, lr=1.0), show_progress=False)
    # NaN at the next epoch: stops with a message, checkpoint of epoch 2 untouched
    before = (run / tr.CHECKPOINT).read_bytes()
    real = tr._pose_step
    monkeypatch.setattr(tr, "_pose_step", lambda *a, **k: (real(*a, **k)[0] * float("nan"), {}))
    with pytest.raises(tr.TrainingDiverged, match=r"loss is nan at epoch 3 step 1.*epoch 2\) kept"):
        tr.train(bop, run, _tiny_train_cfg(epochs=3), show_progress=False)
    assert (run / tr.CHECKPOINT).read_bytes() == before


@pytest.mark.slow
def test_predict_round_trips_through_pose_eval(bop, tmp_path, monkeypatch):
    from presim.pose.evaluate import EvalConfig, evaluate_files
    from presim.pose.nets import train as tr
    from presim.pose.nets.predict import PredictConfig, predict
    from presim.pose.results import read_bop_results, write_bop_results

    monkeypatch.setattr(tr.TrainConfig, "model_config",
                        lambda self, n: ModelConfig(arch=self.model, n_objects=n, **TINY))
    run = tmp_path / "run"
    tr.train(bop, run, _tiny_train_cfg(model="cgaf-noatt", epochs=1), show_progress=False)
    est = predict(bop, run, PredictConfig(split="test"), show_progress=False)
    assert len(est) == 8
    csv = tmp_path / "results.csv"
    write_bop_results(csv, est)
    back = read_bop_results(csv, strict=True).estimates
    assert [(e.scene_id, e.im_id, e.obj_id) for e in back] == [(e.scene_id, e.im_id, e.obj_id) for e in est]
    for a, b in zip(est, back):
        np.testing.assert_allclose(b.R, a.R, atol=1e-6)
        np.testing.assert_allclose(b.t_m, a.t_m, atol=1e-9)
    rep = evaluate_files(bop, csv, EvalConfig(split="test", vsd="off"))
    assert rep.overall["n_targets"] == 8 and rep.overall["n_estimated"] == 8
    assert rep.overall["n_rejected_rows"] == 0


@pytest.mark.slow
def test_segmentation_train_predict_and_iou(bop, tmp_path, capsys):
    """Segmentation run -> pose-predict on its masks (CLI) -> BOP CSV pose-eval reads; IoU per object."""
    from presim.cli import main
    from presim.pose.nets import train as tr
    from presim.pose.nets.segmentation import load_seg_net, segment, segmentation_iou
    from presim.pose.results import read_bop_results

    seg_run, pose_run = tmp_path / "seg", tmp_path / "pose"
    tr.train(bop, seg_run, _tiny_train_cfg(model="segmentation", epochs=2, lr=5e-3), show_progress=False)
    assert "miou_objects" in (seg_run / "metrics.csv").read_text().splitlines()[0]
    net, cfg = load_seg_net(seg_run)
    lab = segment(net, cfg, np.zeros((H, W, 3), np.uint8))
    assert lab.shape == (H, W) and lab.dtype == np.int64 and lab.max() <= 2
    iou = segmentation_iou(bop, seg_run, "test")
    assert set(iou) == {1, 2} and all(0.0 <= v <= 1.0 for v in iou.values())
    # the CLI's segmentation recipe uses its own learning rate unless --lr is given
    seg_cli = tmp_path / "seg_cli"
    assert main(["pose-train", "--dataset", str(bop), "--split", "test", "--model", "segmentation", "--out",
                 str(seg_cli), "--epochs", "1"]) == 0
    assert json.loads((seg_cli / "config.json").read_text())["lr"] == tr.QUICK_SEG_LR != tr.TrainConfig().lr
    # a pose run (tiny) through the CLI with the segmentation in front
    rc = main(["pose-train", "--dataset", str(bop), "--split", "test", "--model", "densefusion", "--out",
               str(pose_run), "--epochs", "1", "--points", "32", "--batch-size", "4"])
    assert rc == 0
    out = tmp_path / "seg.csv"
    assert main(["pose-predict", "--dataset", str(bop), "--checkpoint", str(pose_run), "--segmentation",
                 str(seg_run), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "segmentation IoU per object: 1:" in text
    res = read_bop_results(out, strict=True)
    assert all(e.obj_id in (1, 2) for e in res.estimates)
    # wrong kind of run for each flag: one-line errors
    assert main(["pose-predict", "--dataset", str(bop), "--checkpoint", str(seg_run), "--out", str(out)]) == 1
    assert "is a segmentation run" in capsys.readouterr().err
