"""Batched rendering on torch: B target cameras in one set of tensor operations (CUDA when present).

The per-frame core (:func:`presim.synthesis.core.synthesize_frame`) decides view by view whether
another view is needed; that sequential loop does not batch. This path renders every frame from a
**fixed number** of its selected views (``views_per_frame``, the first ones of each frame's ordered
candidate list) and does all B x V view images at once:

1. one projection of every (frame, view) pair's points (pairs are gathered from one concatenation
   of the distinct views' points; a view used by several frames is stored once);
2. one z-buffer over flat (pair, layer, pixel) keys: ``scatter_reduce("amin")`` of depths, then an
   ``amin`` of point indices among the depth winners (lowest index wins a tie, as everywhere);
3. the switching median of every layer of every pair (:func:`torch_backend.crack_filter_torch` on
   the (pairs x layers) stack), front-to-back composite of the layers, the seam pass;
4. the merge of the views of a frame in order: a pixel takes the first view that has a value
   (the core's merge with ``hole_dilation_px = 0``: later views only fill holes);
5. the final fill per frame (:func:`presim.synthesis.fill.fill_holes`, on the host).

Definition it is tested against: the per-frame core with ``fixed_views = views_per_frame`` and
``hole_dilation_px = 0`` (reference or torch backend), frame by frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch

from presim.geometry import Intrinsics
from presim.synthesis.fill import fill_holes
from presim.synthesis.torch_backend import TorchView, crack_filter_torch

__all__ = ["BatchConfig", "BatchFrame", "first_nonempty", "synthesize_batch_torch"]


@dataclass(frozen=True)
class BatchConfig:
    """Knobs of :func:`synthesize_batch_torch` (``RenderConfig``: ``batch_views``, ``near_m``,
    ``crack_filter``, ``crack_kernel_px``, ``fill_holes``, ``fill_method``)."""

    views_per_frame: int = 3
    near_m: float = 0.01
    crack_filter: str = "switching_median"
    crack_kernel_px: int = 3
    fill_holes: bool = True
    fill_method: str = "auto"

    def __post_init__(self) -> None:
        if self.views_per_frame < 1:
            raise ValueError("BatchConfig: views_per_frame must be >= 1")


@dataclass(frozen=True)
class BatchFrame:
    """One frame of a batch (numpy, on the host)."""

    color: np.ndarray
    depth_m: np.ndarray
    valid: np.ndarray
    source_view: np.ndarray
    hole_frac: float
    views: list[int]


def first_nonempty(depth: torch.Tensor, color: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Front-to-back over ``dim`` of depth (..., K, H, W) / color (..., K, H, W, 3): the first entry
    with depth > 0. Returns ``(depth, color, index)`` with ``dim`` removed (index -1 = none)."""
    occ = depth > 0
    first = occ.to(torch.uint8).argmax(dim, keepdim=True)  # first maximum = first non-empty
    d = depth.gather(dim, first).squeeze(dim)
    c = color.gather(dim, first.unsqueeze(-1).expand(*first.shape, 3)).squeeze(dim)
    anyv = occ.any(dim)
    idx = torch.where(anyv, first.squeeze(dim), torch.full_like(first.squeeze(dim), -1))
    return torch.where(anyv, d, torch.zeros_like(d)), torch.where(anyv[..., None], c, torch.zeros_like(c)), idx


def synthesize_batch_torch(candidates: Sequence[Sequence[int]], T_cam_worlds: np.ndarray, K: Intrinsics,
                           config: BatchConfig, get_view: Callable[[int, int], tuple[object, TorchView]],
                           ms: dict[str, float] | None = None) -> list[BatchFrame]:
    """Render B frames from their first ``config.views_per_frame`` candidates in one batch.

    Args:
        candidates: per frame, the ordered candidate view ids (scene frame indices).
        T_cam_worlds: (B, 4, 4) world -> target camera.
        K: the target intrinsics (shared by the batch).
        config: :class:`BatchConfig`.
        get_view: ``get_view(b, view_id) -> (cache_key, TorchView)`` for frame b (the key tells which
            prepared point set it is, e.g. (view, level of detail); equal keys are stored once).
        ms: optional dict that receives per-stage milliseconds ("warp", "crack", "composite", "fill").
    Returns:
        B :class:`BatchFrame`.
    """
    B = len(candidates)
    H, W = K.height, K.width
    V = config.views_per_frame
    T = np.asarray(T_cam_worlds, np.float64).reshape(B, 4, 4)
    t0 = time.perf_counter()
    # Pairs (frame, slot, view) and the distinct point sets they use.
    pairs: list[tuple[int, int, int]] = []
    keys: dict[object, int] = {}
    tviews: list[TorchView] = []
    pair_set: list[int] = []
    for b, cand in enumerate(candidates):
        for j, vid in enumerate(list(cand)[:V]):
            key, tv = get_view(b, int(vid))
            if key not in keys:
                keys[key] = len(tviews)
                tviews.append(tv)
            pairs.append((b, j, int(vid)))
            pair_set.append(keys[key])
    if not pairs:
        return [_finish(np.zeros((H, W), np.float32), np.zeros((H, W, 3), np.uint8), np.full((H, W), -1, np.int32),
                        [], config) for _ in range(B)]
    dev = tviews[0].xyz_world.device
    L = tviews[0].num_layers
    if any(tv.num_layers != L for tv in tviews):
        raise ValueError("all views of a batch must have the same number of layers")
    counts = torch.tensor([tv.xyz_world.shape[0] for tv in tviews], dtype=torch.int64, device=dev)
    offs = torch.zeros_like(counts)
    offs[1:] = torch.cumsum(counts, 0)[:-1]
    xyz = torch.cat([tv.xyz_world for tv in tviews])
    rgb = torch.cat([tv.rgb for tv in tviews])
    layer = torch.cat([tv.layer for tv in tviews])
    P = len(pairs)
    pset = torch.tensor(pair_set, dtype=torch.int64, device=dev)
    n_pair = counts[pset]
    pair_of = torch.repeat_interleave(torch.arange(P, device=dev), n_pair)
    start = torch.zeros(P, dtype=torch.int64, device=dev)
    start[1:] = torch.cumsum(n_pair, 0)[:-1]
    pt = offs[pset][pair_of] + (torch.arange(pair_of.shape[0], device=dev) - start[pair_of])
    M = torch.as_tensor(T[[p[0] for p in pairs], :3, :4], dtype=torch.float32, device=dev)[pair_of]  # (N, 3, 4)
    p = xyz[pt]
    zc = (M[:, 2, :3] * p).sum(1) + M[:, 2, 3]
    xc = (M[:, 0, :3] * p).sum(1) + M[:, 0, 3]
    yc = (M[:, 1, :3] * p).sum(1) + M[:, 1, 3]
    ok = zc > config.near_m
    zs = torch.where(ok, zc, torch.ones_like(zc))
    uf = K.fx * xc / zs + K.cx + 0.5
    vf = K.fy * yc / zs + K.cy + 0.5
    ok &= (uf >= 0) & (uf < W) & (vf >= 0) & (vf < H)
    sel = torch.nonzero(ok).squeeze(1)
    HW = H * W
    key = (pair_of[sel] * L + layer[pt[sel]]) * HW + vf[sel].long() * W + uf[sel].long()
    zk = zc[sel]
    zbuf = torch.full((P * L * HW,), float("inf"), dtype=torch.float32, device=dev)
    zbuf.scatter_reduce_(0, key, zk, reduce="amin")
    win = zk == zbuf[key]
    n_all = xyz.shape[0]
    ibuf = torch.full((P * L * HW,), n_all, dtype=torch.int64, device=dev)
    ibuf.scatter_reduce_(0, key[win], pt[sel][win], reduce="amin")
    has = ibuf < n_all
    color = torch.zeros((P * L * HW, 3), dtype=torch.uint8, device=dev)
    color[has] = rgb[ibuf[has]]
    depth = torch.where(has, zbuf, torch.zeros_like(zbuf))
    _sync(dev)
    t1 = time.perf_counter()
    d, c = crack_filter_torch(depth.view(P * L, H, W), color.view(P * L, H, W, 3), config.crack_filter,
                              config.crack_kernel_px)
    _sync(dev)
    t2 = time.perf_counter()
    d, c, _ = first_nonempty(d.view(P, L, H, W), c.view(P, L, H, W, 3), 1)
    d, c = crack_filter_torch(d, c, config.crack_filter, config.crack_kernel_px)  # seam pass
    # Scatter pairs into the (B, V) grid and merge the views of each frame in order.
    slot = torch.tensor([b * V + j for b, j, _ in pairs], dtype=torch.int64, device=dev)
    grid_d = torch.zeros((B * V, H, W), dtype=torch.float32, device=dev)
    grid_c = torch.zeros((B * V, H, W, 3), dtype=torch.uint8, device=dev)
    grid_d[slot] = d
    grid_c[slot] = c
    md, mc, mi = first_nonempty(grid_d.view(B, V, H, W), grid_c.view(B, V, H, W, 3), 1)
    vid_grid = torch.full((B, V), -1, dtype=torch.int32, device=dev)
    vid_grid.view(-1)[slot] = torch.tensor([v for _, _, v in pairs], dtype=torch.int32, device=dev)
    src = torch.where(mi >= 0, vid_grid.gather(1, mi.clamp(min=0).view(B, -1)).view(B, H, W),
                      torch.full_like(mi, -1, dtype=torch.int32))
    md, mc, src = md.cpu().numpy(), mc.cpu().numpy(), src.cpu().numpy().astype(np.int32)
    t3 = time.perf_counter()
    used = [[v for bb, _, v in pairs if bb == b] for b in range(B)]
    out = [_finish(md[b], mc[b], src[b], used[b], config) for b in range(B)]
    if ms is not None:
        ms.update({"warp": (t1 - t0) * 1e3, "crack": (t2 - t1) * 1e3, "composite": (t3 - t2) * 1e3,
                   "fill": (time.perf_counter() - t3) * 1e3})
    return out


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize()


def _finish(depth: np.ndarray, color: np.ndarray, src: np.ndarray, views: list[int], config: BatchConfig) -> BatchFrame:
    valid = depth > 0
    hole_frac = float(1.0 - valid.mean())
    if config.fill_holes and 0 < hole_frac:
        color, depth = fill_holes(color, depth, valid, config.fill_method)
    return BatchFrame(np.ascontiguousarray(color), np.ascontiguousarray(depth), valid, src, hole_frac, views)
