"""Accuracy-threshold curves and their area (AUC), as PoseCNN/DenseFusion compute them.

PoseCNN's YCB_Video_toolbox (``plot_accuracy_keyframe.m`` + ``VOCap.m``), which DenseFusion and
the thesis (Table 6.2) reuse, computes the AUC of ADD(-S) like this::

    D(D > max_distance) = inf;          % max_distance = 0.1 m
    d = sort(D); n = numel(d);          % n counts every target, failures included
    accuracy = cumsum(ones(1, n)) / n;  % accuracy at distance d(i) is i / n
    mrec = [0; d(finite); 0.1]; mpre = [0; accuracy(finite); accuracy(last finite)];
    mpre = running max of mpre;
    i = find(mrec(2:end) ~= mrec(1:end-1)) + 1;
    ap = sum((mrec(i) - mrec(i-1)) .* mpre(i)) * 10;

:func:`voc_auc` reproduces it exactly (including its right-endpoint rule: the step from d(i-1)
to d(i) is credited with accuracy i/n, and ties take the first of their run), generalised to any
``max_threshold`` (0.1 m for the 0-10 cm curve, 1.0 for errors divided by the object diameter,
i.e. the thesis's "0-100 % of the diameter" curve). Failures and missing estimates are ``inf``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["voc_auc", "accuracy_curve", "accuracy_at", "auc_trapezoid"]


def _errors(errors) -> np.ndarray:
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    if np.any(np.isnan(e)):
        raise ValueError("errors contain NaN; use inf for failures/missing estimates")
    if np.any(e < 0):
        raise ValueError("errors must be >= 0")
    return e


def voc_auc(errors, max_threshold: float = 0.1) -> float:
    """Area under the accuracy-threshold curve on [0, max_threshold], normalised to [0, 1], with
    YCB_Video_toolbox's VOCap accumulation (see module doc). ``errors`` (n,), inf = failure.

    Example:
        >>> voc_auc([0.05], 0.1)   # one pose at 5 cm: accuracy 1 credited from 0 to 0.1
        1.0
        >>> voc_auc([0.05, np.inf], 0.1)
        0.5
    """
    e = _errors(errors)
    n = e.size
    if n == 0:
        return float("nan")
    d = np.sort(e)
    d[d > max_threshold] = np.inf
    acc = np.arange(1, n + 1, dtype=np.float64) / n
    fin = np.isfinite(d)
    rec, prec = d[fin], acc[fin]
    if rec.size == 0:
        return 0.0
    mrec = np.concatenate([[0.0], rec, [max_threshold]])
    mpre = np.concatenate([[0.0], prec, [prec[-1]]])
    mpre = np.maximum.accumulate(mpre)
    i = np.nonzero(mrec[1:] != mrec[:-1])[0] + 1
    return float(np.sum((mrec[i] - mrec[i - 1]) * mpre[i]) / max_threshold)


def accuracy_curve(errors, thresholds) -> np.ndarray:
    """Fraction of errors strictly below each threshold (BOP's ``error < th``), (T,)."""
    e = _errors(errors)
    th = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    if e.size == 0:
        return np.full(th.shape, np.nan)
    s = np.sort(e)
    return np.searchsorted(s, th, side="left") / e.size


def accuracy_at(errors, threshold: float) -> float:
    """Fraction of errors < ``threshold`` (e.g. ADD(-S) < 2 cm)."""
    return float(accuracy_curve(errors, [threshold])[0])


def auc_trapezoid(errors, max_threshold: float, n_steps: int = 1000) -> float:
    """Plain mean of the accuracy curve on a uniform grid of ``n_steps`` thresholds in
    (0, max_threshold] (a Riemann sum of the exact curve; converges to the true area)."""
    th = np.linspace(0.0, max_threshold, n_steps + 1)[1:]
    return float(np.mean(accuracy_curve(errors, th)))
