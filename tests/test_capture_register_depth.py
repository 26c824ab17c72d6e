"""Depth registration (depth camera -> color camera): known answers on a synthetic plane, numba vs
reference, and the real APC raw depth against the toolbox's registered depth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from presim.capture.register_depth import register_depth, register_depth_reference  # noqa: E402
from presim.geometry import Intrinsics, make_pose, rotation_z  # noqa: E402


def test_plane_translation_known_shift():
    """Fronto-parallel plane at Z seen by a depth camera shifted by b along x: in the color camera the
    plane keeps depth Z and the valid region moves by fx * b / Z pixels."""
    K = Intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)
    Z, b = 2.0, 0.2  # -> 10 px shift
    depth = np.full((48, 64), Z, np.float32)
    T_color_depth = make_pose(np.eye(3), [b, 0.0, 0.0])  # depth camera sits at x = -b in color frame
    out = register_depth(depth, K, K, T_color_depth)
    valid = out > 0
    np.testing.assert_allclose(out[valid], Z, rtol=1e-6)
    # points move +b in color frame -> image shifts right by 10 px: columns 0..9 are empty
    assert not valid[:, :10].any() and valid[:, 10:].all()


def test_plane_depth_changes_with_z_offset_and_magnification():
    """Depth camera 5 cm behind the color camera and a lower focal length: every covered pixel reads
    Z - 0.05, and the footprint splat leaves no pinholes inside the covered area (1.29x magnification)."""
    Kd = Intrinsics(80.0, 80.0, 31.5, 23.5, 64, 48)
    Kc = Intrinsics(100.0, 100.0, 69.5, 49.5, 140, 100)
    Z = 1.5
    out = register_depth(np.full((48, 64), Z, np.float32), Kd, Kc, make_pose(np.eye(3), [0.0, 0.0, -0.05]))
    valid = out > 0
    np.testing.assert_allclose(out[valid], Z - 0.05, rtol=1e-6)
    vs, us = np.nonzero(valid)
    box = valid[vs.min():vs.max() + 1, us.min():us.max() + 1]
    assert box.all()  # no holes from the magnification
    # the covered box matches the projected footprint of the depth image's border
    x_edge = (63.5 - 31.5) / 80.0 * Z  # right edge of the last depth pixel at depth Z
    u_edge = 100.0 * x_edge / (Z - 0.05) + 69.5
    assert u_edge < 139  # the footprint lies inside the color image
    assert us.max() == int(np.floor(u_edge))


def test_occlusion_nearest_wins_and_disocclusion_width():
    """A post at 1 m in front of a wall at 3 m, baseline 0.1 m, f = 60 px: the post shifts 6 px, the
    wall 2 px; the post covers the wall where they overlap and a 4 px gap opens behind it."""
    K = Intrinsics(60.0, 60.0, 15.5, 11.5, 32, 24)
    d = np.full((24, 32), 3.0, np.float32)
    d[:, 4:8] = 1.0
    out = register_depth(d, K, K, make_pose(np.eye(3), [0.1, 0.0, 0.0]))
    row = out[5]
    np.testing.assert_allclose(row[0:2], 0.0)
    np.testing.assert_allclose(row[2:6], 3.0, rtol=1e-6)
    np.testing.assert_allclose(row[6:10], 0.0)   # disocclusion
    np.testing.assert_allclose(row[10:14], 1.0, rtol=1e-6)  # post wins over the wall
    np.testing.assert_allclose(row[14:], 3.0, rtol=1e-6)
    assert np.all(out == out[5])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_numba_matches_reference(seed):
    rng = np.random.default_rng(seed)
    Kd = Intrinsics(70.0, 72.0, 30.0, 22.0, 60, 45)
    Kc = Intrinsics(90.0, 91.0, 40.2, 29.7, 80, 60)
    d = rng.uniform(0.4, 3.0, (45, 60)).astype(np.float32)
    d[rng.random((45, 60)) < 0.2] = 0
    T = make_pose(rotation_z(0.05) @ np.array([[1, 0, 0], [0, np.cos(0.03), -np.sin(0.03)],
                                              [0, np.sin(0.03), np.cos(0.03)]]), [0.025, -0.001, 0.004])
    np.testing.assert_array_equal(register_depth(d, Kd, Kc, T), register_depth_reference(d, Kd, Kc, T))


def test_bad_inputs():
    K = Intrinsics(60.0, 60.0, 15.5, 11.5, 32, 24)
    with pytest.raises(ValueError, match="depth shape"):
        register_depth(np.ones((10, 10), np.float32), K, K, np.eye(4))
    T = np.eye(4)
    T[:3, :3] *= 2
    with pytest.raises(ValueError, match="T_color_depth"):
        register_depth(np.ones((24, 32), np.float32), K, K, T)


def test_real_apc_raw_depth_matches_toolbox_registration(shared_data):
    """Registering raw/ with depth K + extrinsic reproduces the toolbox's registered depth: ~4 mm
    median difference (the toolbox keeps the depth camera's z; the extrinsic has t_z = 4.3 mm), and
    the inverse extrinsic is clearly worse (checks the direction T_color_depth)."""
    from presim.capture.importers import apc_shelf
    from presim.geometry import invert
    from presim.io_utils import read_image

    src = shared_data("apc_shelf_scene0000")
    reg = apc_shelf.read(src)
    raw = apc_shelf.read(src, raw_depth=True)
    dc = raw.frames.depth_camera
    for i in (0, 7):
        d_tool = reg.depth(i)
        d_ours = raw.depth(i)
        both = (d_tool > 0) & (d_ours > 0)
        diff = np.abs(d_tool - d_ours)[both]
        assert both.mean() > 0.15
        assert np.median(diff) < 0.006 and np.percentile(diff, 90) < 0.01
        raw_m = apc_shelf.decode_apc_depth(read_image(raw.frames.depth_paths[i], kind="depth"), Path("x"))
        wrong = register_depth(raw_m, dc.K, raw.intrinsics[0], invert(dc.T_color_depth))
        both_w = (d_tool > 0) & (wrong > 0)
        assert np.median(np.abs(d_tool - wrong)[both_w]) > 2 * np.median(diff)


def test_folder_capture_with_separate_depth_camera(tmp_path, monkeypatch):
    """A kinfu folder whose depth images come from their own camera (depth-intrinsics.txt +
    depth-to-color.txt) is registered at import: a plane at 2 m stays at 2 m - t_z in color."""
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")
    from test_capture_writers import synth_frames, write_kinfu

    from presim.capture.importers import import_capture
    from presim.capture.scene import SceneError
    from presim.io_utils import write_png

    f = synth_frames(n=2)  # color 40x30
    src = write_kinfu(tmp_path / "cap", f)
    Kd = Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)
    for i in range(2):
        write_png(src / f"frame-{i:06d}.depth.png", np.full((24, 32), 2000, np.uint16))
    np.savetxt(src / "depth-intrinsics.txt", Kd.K)
    T = make_pose(np.eye(3), [0.025, 0.0, 0.01])
    np.savetxt(src / "depth-to-color.txt", T)
    s = import_capture(src, align_floor=False)
    d = s.frame(1).depth_m
    assert d.shape == (30, 40)
    np.testing.assert_array_equal(d, register_depth(np.full((24, 32), 2.0, np.float32), Kd, f.K, T))
    np.testing.assert_allclose(d[d > 0], 2.01, rtol=1e-6)
    assert any("registered" in n for n in s.meta.notes)
    (src / "depth-to-color.txt").unlink()
    with pytest.raises(SceneError, match="depth-to-color.txt: not found"):
        import_capture(src, align_floor=False)
