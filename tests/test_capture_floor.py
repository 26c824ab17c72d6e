"""Floor / gravity: synthetic tilted room with a known answer, tabletop without a floor, given gravity,
and the real captures (all tabletop / shelf / bin views: no floor, gravity kept)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_capture_writers import synth_frames, write_kinfu  # noqa: E402

from presim.capture.floor import (  # noqa: E402
    FloorConfig, estimate_floor, gravity_from_cameras, rotation_between,
)
from presim.capture.importers import import_capture  # noqa: E402
from presim.geometry import look_at, make_pose, transform_points  # noqa: E402


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")


def _room(rng, with_floor=True):
    """Points of a 4 x 3 m room in a z-up frame: floor z=0, a table top at z=0.75 (1.2 x 0.8 m),
    two walls, noise 3 mm; cameras at 1.4 m looking around and slightly down."""
    pts = []
    if with_floor:
        pts.append(np.c_[rng.uniform(-2, 2, 40000), rng.uniform(-1.5, 1.5, 40000), np.zeros(40000)])
    pts.append(np.c_[rng.uniform(-0.6, 0.6, 8000), rng.uniform(-0.4, 0.4, 8000), np.full(8000, 0.75)])
    pts.append(np.c_[np.full(20000, 2.0), rng.uniform(-1.5, 1.5, 20000), rng.uniform(0, 2.5, 20000)])
    pts.append(np.c_[rng.uniform(-2, 2, 20000), np.full(20000, 1.5), rng.uniform(0, 2.5, 20000)])
    xyz = np.concatenate(pts) + rng.normal(0, 0.003, (sum(len(p) for p in pts), 3))
    cams = []
    for a in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        eye = np.array([0.3 * np.cos(a), 0.3 * np.sin(a), 1.4])
        cams.append(look_at(eye, eye + np.array([np.cos(a), np.sin(a), -0.4])))
    return xyz, np.stack(cams)


def _tilt():
    ax = np.array([0.3, -0.8, 0.2])
    ax /= np.linalg.norm(ax)
    ang = np.radians(35.0)
    K = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
    R = np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
    return make_pose(R, [0.5, -2.0, 3.0])  # T_capture_zup: an arbitrary capture world


def test_rotation_between():
    for a, b in [([1, 0, 0], [0, 0, 1]), ([0, 0, 1], [0, 0, -1]), ([0.2, 0.3, 0.9], [0, 0, 1])]:
        R = rotation_between(np.array(a, float), np.array(b, float))
        np.testing.assert_allclose(R @ (np.array(a) / np.linalg.norm(a)), b, atol=1e-12)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)


def test_gravity_from_cameras():
    T = np.stack([look_at([0, 0, 1], [1, 0, 1]), look_at([0, 0, 1], [0, 1, 1])])
    g, cons = gravity_from_cameras(T)
    np.testing.assert_allclose(g, [0, 0, -1], atol=1e-12)
    assert cons == pytest.approx(1.0)


def test_tilted_room_known_floor():
    rng = np.random.default_rng(0)
    xyz, cams = _room(rng)
    T = _tilt()
    res = estimate_floor(transform_points(T, xyz), np.einsum("ij,njk->nik", T, cams))
    assert res.floor is not None
    # the true floor normal in the capture world is R @ z; offset: n . p + d = 0 at p = T @ 0
    n_true = T[:3, :3] @ np.array([0, 0, 1.0])
    np.testing.assert_allclose(res.floor.normal, n_true, atol=2e-3)
    assert res.floor.offset == pytest.approx(-n_true @ T[:3, 3], abs=3e-3)
    np.testing.assert_allclose(res.gravity_world, -n_true, atol=2e-3)
    # applying the transform: floor points at z = 0, the table at 0.75 m, no scale change
    floor_pts = transform_points(T, xyz[:40000])
    z = transform_points(res.T_aligned_world, floor_pts)[:, 2]
    assert abs(np.median(z)) < 2e-3
    table = transform_points(res.T_aligned_world, transform_points(T, xyz[40000:48000]))[:, 2]
    assert np.median(table) == pytest.approx(0.75, abs=5e-3)
    np.testing.assert_allclose(np.linalg.svd(res.T_aligned_world[:3, :3])[1], 1.0, atol=1e-12)


def test_lowest_large_plane_wins_over_bigger_table():
    """A floor seen only in part (fewer points than a big table) is still chosen: it is lower."""
    rng = np.random.default_rng(1)
    floor = np.c_[rng.uniform(-2, 0, 6000), rng.uniform(-1, 0, 6000), np.zeros(6000)]
    table = np.c_[rng.uniform(-1, 1, 20000), rng.uniform(-1, 1, 20000), np.full(20000, 0.7)]
    cams = np.stack([look_at([0, 0, 1.5], [1, 0, 0.5]), look_at([0, 0, 1.5], [0, 1, 0.5])])
    res = estimate_floor(np.concatenate([table, floor]), cams)
    assert res.floor is not None and res.floor.offset == pytest.approx(0.0, abs=2e-3)


def test_tabletop_without_floor_keeps_frame():
    rng = np.random.default_rng(2)
    table = np.c_[rng.uniform(-0.4, 0.4, 20000), rng.uniform(-0.3, 0.3, 20000), np.full(20000, 0.7)]
    box = np.c_[rng.uniform(-0.1, 0.1, 3000), np.full(3000, 0.0), rng.uniform(0.7, 0.9, 3000)]
    cams = np.stack([look_at([0.5, 0, 1.2], [0, 0, 0.7]), look_at([0, 0.5, 1.2], [0, 0, 0.7])])
    res = estimate_floor(np.concatenate([table, box]), cams)
    assert res.floor is None and res.T_aligned_world is None
    assert "no floor found" in res.note and "covers only" in res.note
    assert res.gravity_world[2] < -0.8  # still a sensible gravity estimate


def test_given_gravity_overrides_cameras():
    """Cameras all tipped 90 deg about world x (as if mounted sideways) suggest a horizontal gravity;
    the given gravity still finds the floor."""
    rng = np.random.default_rng(3)
    xyz, cams = _room(rng)
    tip = make_pose(np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]]), [0, 0, 0])
    rolled = np.einsum("ij,njk->nik", tip, cams)
    rolled[:, :3, 3] = cams[:, :3, 3]
    g_cam = estimate_floor(xyz, rolled).gravity_world
    assert abs(g_cam[2]) < 0.2  # the camera-based guess is horizontal, i.e. wrong
    assert estimate_floor(xyz, rolled).floor is None or \
        abs(estimate_floor(xyz, rolled).floor.normal[2]) < 0.9
    res = estimate_floor(xyz, rolled, gravity=np.array([0, 0, -9.81]))
    assert res.floor is not None and res.floor.normal[2] == pytest.approx(1.0, abs=1e-3)
    with pytest.raises(ValueError, match="gravity"):
        estimate_floor(xyz, rolled, gravity=np.array([0, 0, 0.0]))


def test_align_scene_end_to_end(tmp_path):
    """A kinfu capture of a synthetic tilted floor: import aligns it (floor z = 0, gravity -z), the
    applied transform is recorded and never scales."""
    f = synth_frames(n=6, w=48, h=36, seed=4)
    T = _tilt()
    # depth of the plane z = 0 (in the z-up frame) seen from cameras 1.4 m above it looking down
    cams_zup = []
    for a in np.linspace(0, 2 * np.pi, 6, endpoint=False):
        eye = np.array([np.cos(a), np.sin(a), 1.4])
        cams_zup.append(look_at(eye, eye + np.array([0.5 * np.cos(a), 0.5 * np.sin(a), -1.0])))
    cams_zup = np.stack(cams_zup)
    K = f.K
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    for i, Tc in enumerate(cams_zup):
        rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], -1) @ Tc[:3, :3].T
        z = -Tc[2, 3] / rays[..., 2]  # ray parameter where world z = 0; equals camera z-depth
        f.depth_mm[i] = np.clip(np.round(z * 1000), 0, 65000).astype(np.uint16)
    f.T_world_cam[:] = np.einsum("ij,njk->nik", T, cams_zup)
    src = write_kinfu(tmp_path / "cap", f)
    s = import_capture(src, floor_config=FloorConfig(min_area_m2=0.5))
    assert s.floor is not None and [t.name for t in s.meta.transforms] == ["floor_alignment"]
    np.testing.assert_array_equal(s.gravity_world, [0, 0, -1])
    z = s.points.xyz[:, 2]
    assert np.abs(z).max() < 0.01
    np.testing.assert_allclose(s.T_world_cam[:, 2, 3], 1.4, atol=0.01)  # cameras back at 1.4 m
    A = s.meta.transforms[0].T_new_old
    np.testing.assert_allclose(A[:3, :3] @ A[:3, :3].T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("name", ["apc_cardboard_bin_kinfu50", "apc_shelf_scene0000", "ycbv_2frames"])
def test_real_captures_have_no_floor(shared_data, name):
    """None of the real captures shows a floor (a bin, a shelf bin, table-top frames): the world frame
    is kept, gravity comes from the cameras and the note says why."""
    s = import_capture(shared_data(name))
    assert s.floor is None and s.meta.transforms == ()
    assert any(n.startswith("no floor found") for n in s.meta.notes)
    assert np.linalg.norm(s.gravity_world) == pytest.approx(1.0)
    if name == "apc_shelf_scene0000":
        # its world is z-up (bin-to-world); camera-based gravity is within ~15 deg of -z
        assert s.gravity_world[2] < -0.96
