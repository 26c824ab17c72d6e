"""Evaluations of the pipeline against real captures (thesis §3.5, §4.5): the leave-one-out
view-synthesis protocol with the thesis ablations (:mod:`presim.evaluation.eval_views`), the TSDF-mesh
baseline (:mod:`presim.evaluation.tsdf_baseline`), trajectory metrics (:mod:`presim.evaluation.poses`)
and the sim-to-real depth experiment (:mod:`presim.evaluation.sim2real`). Sits above ``depth`` and
``synthesis`` (it refines depth and renders), beside ``sim`` / ``datasets``; nothing below imports it.
"""
