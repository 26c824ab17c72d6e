"""Camera pose refinement of a captured scene (thesis §5.3.3): local-to-global RGB-D bundle adjustment.

Stages, each one pure function with its config dataclass beside it:

- :mod:`.grouping`  -- ``group_poses``: groups of <= 10 poses around key poses (distance rank, angle
  within the field of view), as §5.3.3.
- :mod:`.features`  -- ``extract_features`` (OpenCV SIFT) and ``match_pair`` (ratio test, then PnP
  RANSAC on the key image's depth: works for pure rotations where a fundamental matrix degenerates).
- :mod:`.bundle`    -- ``adjust_poses``: poses with points anchored in the key frame's depth (thesis eq.
  5.1), reprojection and depth residuals, Huber loss (scipy ``least_squares``, sparse Jacobian);
  ``bundle_adjust``: the same with free 3D points (slower; not used by the pipeline).
- :mod:`.pipeline`  -- ``align_poses``: local BA per group, global BA of the key poses, an optional joint
  pass over all frames, the rigid fit that keeps the scene's world frame, and the per-frame acceptance
  test (a frame keeps its given pose unless the refined one measurably lowers its reprojection
  residuals; kept frames anchor a re-adjustment of the others; per-frame uncertainty).
- :mod:`.sfm`       -- ``estimate_poses_sfm``: initial poses of a capture without poses (pycolmap
  incremental SfM, metric scale from the depth); ``estimate_poses``: that, then ``align_poses`` (what
  ``presim import`` passes to ``import_capture`` for such a capture).

A sub-package above ``capture`` (docs/layout.md): it reads and returns scenes, and ``capture`` never
imports it.

See docs/alignment.md.
"""

from presim.align.pipeline import AlignConfig, AlignError, AlignResult, align_poses

__all__ = ["AlignConfig", "AlignError", "AlignResult", "align_poses"]
