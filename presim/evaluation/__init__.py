"""Evaluations of the pipeline against real captures (thesis §3.5, §4.5).

Sub-modules: :mod:`presim.evaluation.sim2real` (issue 15: monocular depth trained on synthesized
views vs on the capture alone, tested on real frames away from the capture).
"""
