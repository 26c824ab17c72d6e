"""6D pose metrics and the benchmark evaluator (thesis §6.3.1): bop_toolkit-compatible errors
(numpy reference + torch batch + fast exact ADD-S), AUC curves, BOP results reader, evaluator and
report (``presim pose-eval``). See docs/pose-metrics.md.

Modules are imported on demand (``from presim.pose.metrics import add``) so that importing the
package stays cheap.
"""
