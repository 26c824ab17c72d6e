"""Torch versions of the image operations (float32; CUDA when present, else CPU): the Gaussian filter, pull-push
fill and 8-connected component labels. Host arrays in and out (labels: tensors); each is tested against its numpy /
numba version. The only module of :mod:`presim.imaging` that imports torch."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch
import torch.nn.functional as F

from presim.imaging.gaussian import MIN_SIGMA_PX, check_smooth_input, gaussian_taps

__all__ = ["resolve_device", "to_tensor", "smooth_colors_torch", "pushpull_rgbd_torch", "label_components_torch"]


def resolve_device(name: str | None = None) -> torch.device:
    """``torch.device(name)``, or CUDA when present, else CPU when ``name`` is None / empty."""
    return torch.device(name if name else "cuda" if torch.cuda.is_available() else "cpu")


def to_tensor(a: np.ndarray, dev: torch.device) -> torch.Tensor:
    """A host array as a tensor on ``dev`` (contiguous; no copy on the CPU when it is already)."""
    return torch.from_numpy(np.ascontiguousarray(a)).to(dev)


def smooth_colors_torch(color: np.ndarray, sigma_px: float, device=None) -> np.ndarray:
    """:func:`~presim.imaging.gaussian.smooth_colors_ref` as two float32 1-D convolutions in torch (CUDA when
    present), within one grey level of the reference. New uint8 (H, W, 3)."""
    check_smooth_input(color, sigma_px)
    if sigma_px < MIN_SIGMA_PX:
        return color.copy()
    dev = resolve_device(device)
    t = torch.as_tensor(gaussian_taps(sigma_px), dtype=torch.float32, device=dev)
    r = len(t) // 2
    x = torch.from_numpy(np.ascontiguousarray(color)).to(dev).permute(2, 0, 1)[:, None].float()  # (3, 1, H, W)
    f = torch.nn.functional
    x = f.conv2d(f.pad(x, (r, r, 0, 0), mode="reflect"), t.view(1, 1, 1, -1))
    x = f.conv2d(f.pad(x, (0, 0, r, r), mode="reflect"), t.view(1, 1, -1, 1))
    out = torch.floor(x[:, 0] + 0.5).clamp(0, 255).to(torch.uint8).permute(1, 2, 0)
    return out.cpu().numpy()


@functools.lru_cache(maxsize=64)
def _area_taps(n: int, n2: int) -> tuple[np.ndarray, np.ndarray]:
    """``(index, weight)`` (n2, 3) of OpenCV's INTER_AREA from n to n2 (n / 2 <= n2 <= n) samples, as its
    ``computeResizeAreaTab`` (unused taps: weight 0)."""
    idx, wt = np.zeros((n2, 3), np.int64), np.zeros((n2, 3), np.float32)
    s = n / n2
    for j in range(n2):
        f1 = j * s
        f2, cell = f1 + s, min(s, n - f1)
        s2 = min(math.floor(f2), n - 1)
        s1 = min(math.ceil(f1), s2)
        taps = ([(s1 - 1, (s1 - f1) / cell)] if s1 - f1 > 1e-3 else []) + [(x, 1.0 / cell) for x in range(s1, s2)]
        taps += [(s2, min(f2 - s2, 1.0, cell) / cell)] if f2 - s2 > 1e-3 else []
        for k, (x, w) in enumerate(taps):
            idx[j, k], wt[j, k] = x, w
    return idx, wt


def _area_halve(x: torch.Tensor) -> torch.Tensor:
    """(C, h, w) -> (C, ceil(h / 2), ceil(w / 2)) as ``cv2.resize(INTER_AREA)``."""
    for dim in (2, 1):
        n = x.shape[dim]
        idx, wt = (torch.from_numpy(t).to(x.device) for t in _area_taps(n, (n + 1) // 2))
        x = (x.movedim(dim, -1)[..., idx] * wt).sum(-1).movedim(-1, dim)
    return x


def pushpull_rgbd_torch(color: np.ndarray | None, depth_m: np.ndarray, valid: np.ndarray,
                        device: torch.device | str | None = None) -> tuple[np.ndarray | None, np.ndarray]:
    """:func:`~presim.imaging.pushpull.pushpull_rgbd` in torch (float32): pull = OpenCV area halving of the
    premultiplied values and weights, push = bilinear upsampling (``align_corners=False`` = INTER_LINEAR) blended
    by ``clip(w, 0, 1)``. Known pixels unchanged; the rest within float32 rounding of
    :func:`~presim.imaging.pushpull.pushpull_fill`."""
    dev = resolve_device(device)
    known = to_tensor(valid, dev).bool()
    d = to_tensor(np.asarray(depth_m, np.float32), dev)
    c = None if color is None else to_tensor(color, dev)
    v = d[None] if c is None else torch.cat([c.permute(2, 0, 1).float(), d[None]])
    acc, w = torch.where(known, v, 0.0), known.float()
    levels = []
    while not bool((w > 0).all()) and min(w.shape) > 1:
        levels.append((acc, w))
        both = _area_halve(torch.cat([acc, w[None]]))
        acc, w = both[:-1], both[-1]
    est = acc / w.clamp(min=1e-12)
    for acc_l, w_l in reversed(levels):
        up = F.interpolate(est[None], size=w_l.shape, mode="bilinear", align_corners=False)[0]
        a = w_l.clamp(0.0, 1.0)
        est = acc_l / w_l.clamp(min=1e-12) * a + up * (1.0 - a)
    out_d = torch.where(known, d, est[-1]).cpu().numpy()
    if c is None:
        return None, out_d
    rounded = (est[:3] + 0.5).clamp(0.0, 255.0).to(torch.uint8).permute(1, 2, 0)
    return torch.where(known[..., None], c, rounded).cpu().numpy(), out_d


def label_components_torch(mask: torch.Tensor) -> torch.Tensor:
    """int64 (H, W) 8-connected components of a bool (H, W) mask: every pixel of a component holds the smallest
    flat index in it, -1 outside. Roots hook onto the smaller root across each edge, then pointer jumping, until
    no edge joins two roots (Shiloach-Vishkin style; O(log n) rounds on the masks tested)."""
    H, W = mask.shape
    idx = torch.arange(H * W, device=mask.device).view(H, W)
    ends = []
    for dy, dx in ((0, 1), (1, -1), (1, 0), (1, 1)):  # each 8-neighbour pair once
        x0, x1 = max(0, -dx), W - max(0, dx)
        both = mask[:H - dy, x0:x1] & mask[dy:, x0 + dx:x1 + dx]
        ends.append((idx[:H - dy, x0:x1][both], idx[dy:, x0 + dx:x1 + dx][both]))
    a, b = torch.cat([e[0] for e in ends]), torch.cat([e[1] for e in ends])
    parent = idx.reshape(-1).clone()
    while len(a):
        pa, pb = parent[a], parent[b]
        split = pa != pb
        a, b, pa, pb = a[split], b[split], pa[split], pb[split]  # joined edges stay joined
        parent.scatter_reduce_(0, torch.maximum(pa, pb), torch.minimum(pa, pb), "amin")
        while True:  # parent[i] <= i: no cycle, jumping ends at the roots
            up = parent[parent]
            if torch.equal(up, parent):
                break
            parent = up
    return torch.where(mask.reshape(-1), parent, -1).view(H, W)
