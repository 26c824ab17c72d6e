"""Evaluation of view synthesis against real images (thesis §3.5): the leave-one-out protocol with
the thesis ablations (:mod:`presim.evaluation.eval_views`) and the TSDF-mesh baseline
(:mod:`presim.evaluation.tsdf_baseline`). Sits above ``depth`` and ``synthesis`` (it refines depth
and renders), beside ``sim`` / ``datasets``; nothing below imports it."""
