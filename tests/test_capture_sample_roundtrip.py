"""The clean sample scene written as a KinectFusion capture and imported back: the floor is found at
z = 0 (its world is already floor-aligned, so the alignment is ~identity), and reprojecting a frame into
its neighbour with depth and poses gives a near-zero color error (the issue's "done when")."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from presim.capture.importers import import_capture  # noqa: E402
from presim.capture.reprojection import reprojection_mae  # noqa: E402
from presim.io_utils import write_png  # noqa: E402


@pytest.mark.slow
def test_sample_scene_as_kinfu(tmp_path, monkeypatch):
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")
    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene, clean_scene

    dst = build_sample_scene(tmp_path / "sample", seed=0, config=SampleSceneConfig(width=320, height=240, num_frames=16))
    s = clean_scene(dst)
    cap = tmp_path / "cap"
    cap.mkdir()
    np.savetxt(cap / "camera-intrinsics.txt", s.intrinsics[0].K)
    for i in range(len(s)):
        f = s.frame(i)
        write_png(cap / f"frame-{i:06d}.color.png", f.color)
        write_png(cap / f"frame-{i:06d}.depth.png", np.round(f.depth_m * 1000).astype(np.uint16))
        np.savetxt(cap / f"frame-{i:06d}.pose.txt", f.T_world_cam, fmt="%.17g")
    imp = import_capture(cap)
    assert imp.floor is not None, imp.meta.notes
    A = imp.meta.transforms[0].T_new_old
    np.testing.assert_allclose(A[:3, :3], np.eye(3), atol=5e-3)  # already gravity -z
    assert abs(A[2, 3]) < 0.01  # already floor z = 0
    # reprojection into the neighbour: near zero with poses, large without
    errs = [reprojection_mae(imp, i, i + 1) for i in range(0, len(imp) - 1, 4)]
    base = [reprojection_mae(imp, i, i + 1, use_poses=False)[0] for i in range(0, len(imp) - 1, 4)]
    mae = float(np.mean([e[0] for e in errs]))
    assert mae < 4.0 and mae < 0.2 * float(np.mean(base)), (mae, base)
