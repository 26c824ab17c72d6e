"""Sim-to-real evidence (thesis §4.5, Table 4.3): does training on PreSim's synthesized views help a
monocular depth network on real frames the capture did not see?

    split = split_capture(scene, capture_every=10)          # capture / test frames + distance bins
    poses = synth_poses(split.capture_poses, m=200, seed=0)  # new views around/between capture poses
    run_depth_experiment(scene, recipe_config("default", 9), out_dir)  # three arms, summary.json
    run_capture_sweep(scene, cfg, (10, 25, 50), out_dir)               # gain against capture density

Modules: ``split`` (capture/test split, bins, poses), ``experiment`` (training set, arms, recipes),
``model`` (network and loss), ``metrics``, ``report`` (report.md and figures, RMS against the
distance to the capture), ``sweep`` (capture-density sweep and its crossover).

See docs/sim2real.md for the protocol, the choices and measured results.
"""

from presim.evaluation.sim2real.metrics import depth_metrics
from presim.evaluation.sim2real.split import (BINS, CaptureSplit, SynthPoseConfig, pose_distance,
                                              split_capture, synth_poses)

__all__ = ["BINS", "CaptureSplit", "SynthPoseConfig", "depth_metrics", "pose_distance", "split_capture",
           "synth_poses"]
