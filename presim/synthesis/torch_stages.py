"""Torch kernels of the stages after the view image (``PerfConfig(backend="torch")``): merge + hole analysis, blend and
exposure, each tested against its numba / numpy path (pull-push fill: :mod:`presim.imaging.torch_ops`). Host arrays in
and out, as :mod:`presim.synthesis.torch_kernels`; computed on ``device`` (None: CUDA when present, else CPU)."""

from __future__ import annotations

import functools

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from presim.geometry import Intrinsics
from presim.imaging.feather import feather_box
from presim.imaging.torch_ops import label_components_torch, resolve_device, to_tensor
from presim.photometric.apply import gain_bias_lut
from presim.synthesis.blend import BlendConfig, BlendInput
from presim.synthesis.holes import HoleStats

__all__ = ["merge_holes_torch", "analyse_hole_mask_torch", "blend_torch", "apply_exposure_torch"]


def merge_holes_torch(acc_depth_m: np.ndarray, acc_color: np.ndarray, acc_source: np.ndarray,
                      replace: np.ndarray | None, depth_m: np.ndarray, color: np.ndarray, view_id: int,
                      holes: np.ndarray, device: torch.device | str | None = None) -> int:
    """:func:`~presim.synthesis.holes.merge_view_holes` (``replace`` None: the first view, whose image is the
    accumulator) or :func:`~presim.synthesis.holes.merge_into_holes` (``holes`` the mask before the merge): the
    host arrays updated in place, the same pixels and return value (the hole count; the holes filled)."""
    dev = resolve_device(device)
    has = to_tensor(depth_m, dev) > 0
    if replace is None:
        np.copyto(acc_source, torch.where(has, int(view_id), -1).cpu().numpy(), casting="unsafe")
        h = ~has
        n = h.sum()
    else:
        take = to_tensor(replace, dev).bool() & has
        for acc, new in ((acc_depth_m, depth_m), (acc_color, color), (acc_source, None)):
            a = to_tensor(acc, dev)
            b = torch.full_like(a, int(view_id)) if new is None else to_tensor(new, dev)
            t = take if a.dim() == 2 else take[..., None]
            np.copyto(acc, torch.where(t, b, a).cpu().numpy())
        h = to_tensor(holes, dev).bool()
        n = (h & take).sum()
        h &= ~take
    np.copyto(holes, h.cpu().numpy(), casting="unsafe")
    return int(n)


@functools.lru_cache(maxsize=8)
def _ellipse(k: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)).astype(np.float32)


def analyse_hole_mask_torch(holes: np.ndarray, n_hole: int, big_hole_px: int = 16, hole_dilation_px: int = 2,
                            want_replace: bool = True, stop_px: float = 0.0, want_largest: bool = True,
                            device: torch.device | str | None = None) -> HoleStats:
    """:func:`~presim.synthesis.holes.analyse_hole_mask` in torch (the same :class:`HoleStats`): components by
    :func:`~presim.imaging.torch_ops.label_components_torch`, areas by ``bincount``, big holes dilated by OpenCV's
    elliptic element."""
    H, W = holes.shape
    if n_hole == 0:
        return HoleStats(0.0, 0, np.zeros((H, W), bool) if want_replace else None)
    if n_hole <= stop_px or not (want_largest or want_replace):
        return HoleStats(n_hole / float(H * W), n_hole, None, None)
    dev = resolve_device(device)
    m = to_tensor(holes, dev) != 0
    lab = label_components_torch(m)
    area = torch.bincount(lab[m], minlength=H * W)
    largest = int(area.max())
    if not want_replace:
        return HoleStats(n_hole / float(H * W), largest, None, None)
    big = m & (area[lab.clamp(min=0)] >= big_hole_px)
    rep = m
    if hole_dilation_px > 0:
        el = torch.from_numpy(_ellipse(2 * hole_dilation_px + 1)).to(dev)
        rep = m | (F.conv2d(big.float()[None, None], el[None, None], padding=hole_dilation_px)[0, 0] > 0)
    return HoleStats(n_hole / float(H * W), largest, rep.cpu().numpy(), big.cpu().numpy())


def _feather(depth_m: torch.Tensor, feather_px: float) -> torch.Tensor:
    """:func:`~presim.imaging.feather.feather_map` of (n, H, W) depths, bit for bit (box counts, as
    :func:`~presim.imaging.feather.coverage_counts`)."""
    cov = (depth_m > 0).float()
    if feather_px <= 1:
        return cov
    k = feather_box(feather_px)
    count = F.avg_pool2d(F.pad(cov[:, None], (k // 2,) * 4, mode="replicate"), k, stride=1, divisor_override=1)
    m = (count[:, 0].double() * (1.0 / (k * k))).float()
    return (2.0 * m - 1.0).clamp(0.0, 1.0) * cov


def blend_torch(inp: BlendInput, K: Intrinsics, T_world_cam: np.ndarray, config: BlendConfig,
                device: torch.device | str | None = None) -> np.ndarray:
    """:func:`~presim.synthesis.blend.blend_reference` in torch, float64 as the reference; uint8 (H, W, 3).
    Ignores ``inp.feather_count`` (feathers from the view depths)."""
    dev = resolve_device(device)
    f64 = torch.float64
    d = to_tensor(inp.depth_m, dev).to(f64)
    H, W = d.shape
    T = torch.as_tensor(np.asarray(T_world_cam, np.float64), device=dev)
    v, u = torch.meshgrid(torch.arange(H, dtype=f64, device=dev), torch.arange(W, dtype=f64, device=dev), indexing="ij")
    P = torch.stack([(u - K.cx) / K.fx * d, (v - K.cy) / K.fy * d, d], -1)
    X = P @ T[:3, :3].T + T[:3, 3]
    rt = X - T[:3, 3]
    lt = rt.pow(2).sum(-1).sqrt()
    color, source = to_tensor(inp.color, dev), to_tensor(inp.source, dev)
    vdepth, vcolor = to_tensor(inp.view_depth_m, dev), to_tensor(inp.view_color, dev)
    centres = torch.as_tensor(np.asarray(inp.centres, np.float64), device=dev)
    feather = _feather(vdepth, config.feather_px)
    min_f = torch.tensor(1.0 / config.feather_px, dtype=torch.float32, device=dev)
    num = torch.zeros((H, W, 3), dtype=f64, device=dev)
    den = torch.zeros((H, W), dtype=f64, device=dev)
    cnt = torch.zeros((H, W), dtype=torch.int64, device=dev)
    for k in range(len(inp.view_ids)):
        win = source == int(inp.view_ids[k])
        dk = vdepth[k].to(f64)
        use = (d > 0) & (win | ((dk > 0) & ((dk - d).abs() <= config.depth_tol_rel * d)))
        rk = X - centres[k]
        lk = rk.pow(2).sum(-1).sqrt()
        cosang = ((rt * rk).sum(-1) / (lt * lk)).clamp(-1.0, 1.0)
        pen = (2.0 - 2.0 * cosang).sqrt() + config.resolution_weight * (lk / lt - 1.0).clamp(min=0.0)
        f = torch.where(win, torch.maximum(feather[k], min_f), feather[k]).to(f64)
        w = torch.where(use, f * float(inp.quality[k]) / (pen + config.penalty_eps), 0.0)
        num += w[..., None] * torch.where(win[..., None], color, vcolor[k]).to(f64)
        den += w
        cnt += use
    m = (cnt >= 2) & (den > 0)
    mixed = torch.floor(num / den[..., None] + 0.5).clamp(0, 255).to(torch.uint8)
    return torch.where(m[..., None], mixed, color).cpu().numpy()


def apply_exposure_torch(color: np.ndarray, A: np.ndarray, b: np.ndarray,
                         device: torch.device | str | None = None) -> np.ndarray:
    """:func:`~presim.photometric.apply.apply_exposure` in torch: a diagonal ``A`` gathers from the same
    256-entry tables (equal bytes); any other ``round(clip(A x + b))`` in float64, a channel at 0 stays 0."""
    dev = resolve_device(device)
    A = np.asarray(A, np.float64)
    c = to_tensor(color, dev)
    if np.count_nonzero(A - np.diag(np.diag(A))) == 0:
        lut = to_tensor(gain_bias_lut(np.ones(3), np.zeros(3), np.diag(A), np.asarray(b))[0], dev)  # (256, 3)
        return lut[c.long(), torch.arange(3, device=dev)].cpu().numpy()
    y = c.to(torch.float64) @ torch.as_tensor(A.T, device=dev) + torch.as_tensor(np.asarray(b, np.float64), device=dev)
    return torch.where(c == 0, 0, torch.floor(y + 0.5).clamp(0, 255)).to(torch.uint8).cpu().numpy()
