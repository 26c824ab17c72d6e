"""Torch path of the view image (``PerfConfig(backend="torch")``): CUDA when available, else CPU.

Same rules as :mod:`presim.synthesis.kernels_reference` (tested on CPU): the z-buffer is an ``amin`` scatter of
depths, then of point indices among the winners; the median gathers only the pixels it may change."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from presim.geometry import Intrinsics
from presim.imaging.torch_ops import resolve_device
from presim.synthesis.warp import ViewPoints

__all__ = ["resolve_device", "TorchView", "to_device", "warp_layers_torch",
           "crack_filter_torch", "composite_layers_torch", "view_image_torch"]


@dataclass(frozen=True)
class TorchView:
    """A :class:`ViewPoints` on a torch device."""

    xyz_world: torch.Tensor
    """float32 (n, 3)."""
    rgb: torch.Tensor
    """uint8 (n, 3)."""
    layer: torch.Tensor
    """int64 (n,)."""
    num_layers: int
    image: object = None
    """The view's source image on the host (``ViewPoints.image``), or None."""

    @property
    def nbytes(self) -> int:
        return int(self.xyz_world.numel() * 4 + self.rgb.numel() + self.layer.numel() * 8
                   + (self.image.nbytes if self.image is not None else 0))


def to_device(view: ViewPoints, device: torch.device | str | None = None) -> TorchView:
    device = resolve_device(device)
    return TorchView(torch.from_numpy(view.xyz_world).to(device), torch.from_numpy(view.rgb).to(device),
                     torch.from_numpy(view.layer).to(device), view.num_layers, view.image)


def warp_layers_torch(view: TorchView, T_cam_world: np.ndarray, K: Intrinsics, near_m: float = 1e-3
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Layered z-buffer warp. Returns ``(depth (L, H, W) float32, color (L, H, W, 3) uint8)``."""
    dev = view.xyz_world.device
    L, H, W = view.num_layers, K.height, K.width
    M = torch.as_tensor(np.asarray(T_cam_world, np.float64)[:3, :4], dtype=torch.float32, device=dev)
    x, y, z = view.xyz_world[:, 0], view.xyz_world[:, 1], view.xyz_world[:, 2]
    zc = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + M[2, 3]
    xc = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + M[0, 3]
    yc = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + M[1, 3]
    ok = zc > near_m
    zs = torch.where(ok, zc, torch.ones_like(zc))
    uf = K.fx * xc / zs + K.cx + 0.5
    vf = K.fy * yc / zs + K.cy + 0.5
    ok &= (uf >= 0) & (uf < W) & (vf >= 0) & (vf < H)
    idx = torch.nonzero(ok).squeeze(1)
    key = view.layer[idx] * (H * W) + vf[idx].long() * W + uf[idx].long()
    zk = zc[idx]
    zbuf = torch.full((L * H * W,), float("inf"), dtype=torch.float32, device=dev)
    zbuf.scatter_reduce_(0, key, zk, reduce="amin")
    win = zk == zbuf[key]
    n = view.xyz_world.shape[0]
    ibuf = torch.full((L * H * W,), n, dtype=torch.int64, device=dev)
    ibuf.scatter_reduce_(0, key[win], idx[win], reduce="amin")
    has = ibuf < n
    color = torch.zeros((L * H * W, 3), dtype=torch.uint8, device=dev)
    color[has] = view.rgb[ibuf[has]]
    depth = torch.where(has, zbuf, torch.zeros_like(zbuf))
    return depth.view(L, H, W), color.view(L, H, W, 3)


def _neighbour_offsets(r: int, Wp: int, device) -> torch.Tensor:
    dy, dx = torch.meshgrid(torch.arange(-r, r + 1, device=device), torch.arange(-r, r + 1, device=device),
                            indexing="ij")
    return (dy * Wp + dx).reshape(-1)


def crack_filter_torch(depth_m: torch.Tensor, color: torch.Tensor, mode: str = "switching_median",
                       kernel_px: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """Switching / plain median of (L, H, W) depth and (L, H, W, 3) color stacks (see reference)."""
    if mode == "none":
        return depth_m, color
    if mode not in ("switching_median", "median"):
        raise ValueError(f"unknown crack filter {mode!r}")
    L, H, W = depth_m.shape
    r = kernel_px // 2
    n_win = kernel_px * kernel_px
    dp = torch.nn.functional.pad(depth_m, (r, r, r, r))  # zero padding = empty outside the image
    cp = torch.nn.functional.pad(color.permute(0, 3, 1, 2), (r, r, r, r)).permute(0, 2, 3, 1)
    Hp, Wp = H + 2 * r, W + 2 * r
    off = _neighbour_offsets(r, Wp, depth_m.device)
    dflat, cflat = dp.reshape(-1), cp.reshape(-1, 3)
    switching = mode == "switching_median"
    flat = depth_m.reshape(-1)
    cand = torch.nonzero(flat == 0).squeeze(1) if switching else torch.arange(flat.numel(), device=flat.device)
    ll, rem = cand // (H * W), cand % (H * W)
    nb_idx = (ll * (Hp * Wp) + (rem // W + r) * Wp + (rem % W + r))[:, None] + off[None, :]
    nd = dflat[nb_idx]
    nz = nd > 0 if switching else torch.ones_like(nd, dtype=torch.bool)  # plain: zeros count
    cnt = nz.sum(1)
    if switching:
        sel = 2 * cnt > n_win
        nb_idx, nd, nz, cnt, cand = nb_idx[sel], nd[sel], nz[sel], cnt[sel], cand[sel]
    k = ((cnt - 1) // 2)[:, None]
    d_med = torch.where(nz, nd, torch.full_like(nd, float("inf"))).sort(dim=1).values.gather(1, k)[:, 0]
    nc = cflat[nb_idx].to(torch.int16)  # (P, n_win, 3); 256 marks empty so it sorts last
    nc = torch.where(nz[..., None], nc, torch.full_like(nc, 256))
    c_med = nc.sort(dim=1).values.gather(1, k[:, :, None].expand(-1, 1, 3))[:, 0].to(torch.uint8)
    if not switching:
        c_med = torch.where((d_med > 0)[:, None], c_med, torch.zeros_like(c_med))
    dout = depth_m.reshape(-1).clone()
    cout = color.reshape(-1, 3).clone()
    dout[cand] = d_med
    cout[cand] = c_med
    return dout.view(L, H, W), cout.view(L, H, W, 3)


def composite_layers_torch(depth_m: torch.Tensor, color: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Front-to-back composite of (L, H, W) layers -> (H, W) depth, (H, W, 3) color."""
    occ = depth_m > 0
    first = occ.to(torch.uint8).argmax(0, keepdim=True)  # first maximum = nearest non-empty layer
    d = depth_m.gather(0, first)[0]
    c = color.gather(0, first[..., None].expand(-1, -1, -1, 3))[0]
    anyv = occ.any(0)
    return torch.where(anyv, d, torch.zeros_like(d)), torch.where(anyv[..., None], c, torch.zeros_like(c))


def view_image_torch(view: TorchView, T_cam_world: np.ndarray, K: Intrinsics, near_m: float, crack_filter: str,
                     kernel_px: int) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """Warp + per-layer crack filter + composite + seam pass on every pixel.
    Returns ``(depth_m (H, W), color (H, W, 3), warp_ms, crack_ms, composite_ms)`` as numpy."""
    t0 = time.perf_counter()
    d, c = warp_layers_torch(view, T_cam_world, K, near_m)
    if d.is_cuda:
        torch.cuda.synchronize()
    t1 = time.perf_counter()
    d, c = crack_filter_torch(d, c, crack_filter, kernel_px)
    if d.is_cuda:
        torch.cuda.synchronize()
    t2 = time.perf_counter()
    d, c = composite_layers_torch(d, c)
    d, c = crack_filter_torch(d[None], c[None], crack_filter, kernel_px)
    d, c = d[0].cpu().numpy(), c[0].cpu().numpy()
    return d, c, (t1 - t0) * 1e3, (t2 - t1) * 1e3, (time.perf_counter() - t2) * 1e3


def resample_colors_torch(color: np.ndarray, depth_m: np.ndarray, source: np.ndarray, K: Intrinsics,
                          T_world_cam: np.ndarray, sources, depth_tol: float = 0.05,
                          device: torch.device | str | None = None) -> np.ndarray:
    """:func:`presim.synthesis.resample.resample_colors_ref` in torch (float64; CUDA when present), one
    gather per source view. ``sources``: a :class:`~presim.synthesis.resample.SourceStack`."""
    from presim.synthesis.resample import source_projection

    dev = resolve_device(device)
    f64 = torch.float64
    H, W = depth_m.shape
    out = torch.from_numpy(np.ascontiguousarray(color)).to(dev).reshape(-1, 3).clone()
    s = torch.from_numpy(np.ascontiguousarray(source, np.int64)).to(dev).reshape(-1)
    d = torch.from_numpy(np.ascontiguousarray(depth_m, np.float32)).to(dev).reshape(-1).to(f64)
    for view_id in np.flatnonzero(sources.lut >= 0):
        j = int(sources.lut[view_id])
        idx = torch.nonzero((s == int(view_id)) & (d > 0)).squeeze(1)
        if len(idx) == 0:
            continue
        P = source_projection(K, T_world_cam, sources, j)
        img = torch.from_numpy(sources.colors[j]).to(dev).to(f64)
        dep = torch.from_numpy(sources.depths[j]).to(dev).to(f64)
        hs, ws = dep.shape
        dd = d[idx]
        x = ((idx % W).to(f64) - K.cx) / K.fx * dd
        y = ((idx // W).to(f64) - K.cy) / K.fy * dd
        p0 = P[0, 0] * x + P[0, 1] * y + P[0, 2] * dd + P[0, 3]
        p1 = P[1, 0] * x + P[1, 1] * y + P[1, 2] * dd + P[1, 3]
        zs = P[2, 0] * x + P[2, 1] * y + P[2, 2] * dd + P[2, 3]
        us, vs = p0 / zs, p1 / zs
        inside = (zs > 0) & (us >= 0) & (us <= ws - 1) & (vs >= 0) & (vs <= hs - 1)
        idx, us, vs, zs = idx[inside], us[inside], vs[inside], zs[inside]
        u0, v0 = torch.floor(us).long(), torch.floor(vs).long()
        a, b = us - u0, vs - v0
        u1, v1 = torch.clamp(u0 + 1, max=ws - 1), torch.clamp(v0 + 1, max=hs - 1)
        acc = torch.zeros((len(idx), 3), dtype=f64, device=dev)
        wsum = torch.zeros(len(idx), dtype=f64, device=dev)
        lim = depth_tol * zs
        for uu, vv, w in ((u0, v0, (1 - a) * (1 - b)), (u1, v0, a * (1 - b)), (u0, v1, (1 - a) * b), (u1, v1, a * b)):
            ds = dep[vv, uu]
            w = torch.where((ds > 0) & ((ds - zs).abs() <= lim), w, torch.zeros_like(w))
            acc += w[:, None] * img[vv, uu]
            wsum += w
        use = wsum > 1e-9
        inv = 1.0 / wsum[use]
        out[idx[use]] = torch.floor(acc[use] * inv[:, None] + 0.5).clamp(0, 255).to(torch.uint8)
    return out.reshape(H, W, 3).cpu().numpy()


_NB8 = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def splat_into_holes_torch(points, T_cam_world: np.ndarray, K: Intrinsics, near_m: float, target,
                           device: torch.device | str | None = None) -> int:
    """Torch version of :func:`presim.synthesis.completion.splat_into_holes` (same pixels)."""
    dev = resolve_device(device)
    H, W = K.height, K.width
    holes = torch.from_numpy(np.ascontiguousarray(target.holes != 0)).to(dev).reshape(-1)
    M = torch.as_tensor(np.asarray(T_cam_world, np.float64), device=dev)
    pix_l, z_l, rgb_l, src_l = [], [], [], []
    for cp in points:
        P = torch.as_tensor(np.asarray(cp.xyz_world), device=dev).double()
        x, y, z = (M[r, 0] * P[:, 0] + M[r, 1] * P[:, 1] + M[r, 2] * P[:, 2] + M[r, 3] for r in range(3))
        u = torch.floor(K.fx * x / z + K.cx + 0.5)
        v = torch.floor(K.fy * y / z + K.cy + 0.5)
        ok = (z > near_m) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        pix = (v[ok] * W + u[ok]).long()
        keep = holes[pix]
        pix_l.append(pix[keep])
        z_l.append(z[ok][keep])
        rgb_l.append(torch.as_tensor(np.asarray(cp.rgb), device=dev)[ok][keep])
        src_l.append(torch.full((int(keep.sum()),), int(cp.view_id), dtype=torch.int32, device=dev))
    zbuf = torch.zeros(H * W, dtype=torch.float64, device=dev)
    cbuf = torch.zeros((H * W, 3), dtype=torch.uint8, device=dev)
    sbuf = torch.full((H * W,), -1, dtype=torch.int32, device=dev)
    if pix_l and sum(len(p) for p in pix_l):
        pix, z, rgb, src = torch.cat(pix_l), torch.cat(z_l), torch.cat(rgb_l), torch.cat(src_l)
        zmin = torch.full((H * W,), float("inf"), dtype=torch.float64, device=dev).scatter_reduce(0, pix, z, "amin")
        win = z == zmin[pix]
        n = len(z)  # the first point (in view order) of the nearest ones wins, as in the kernel
        first = torch.full((H * W,), n, dtype=torch.long, device=dev).scatter_reduce(
            0, pix[win], torch.arange(n, device=dev)[win], "amin")
        hit = first < n
        zbuf[hit], cbuf[hit], sbuf[hit] = z[first[hit]], rgb[first[hit]], src[first[hit]]
    zb, cb, sb = zbuf.reshape(H, W), cbuf.reshape(H, W, 3), sbuf.reshape(H, W)
    pad = torch.nn.functional.pad(torch.where(zb > 0, zb, torch.full_like(zb, float("inf"))), (1, 1, 1, 1),
                                  value=float("inf"))
    shifted = torch.stack([pad[1 + dy:1 + dy + H, 1 + dx:1 + dx + W] for dy, dx in _NB8])
    count = torch.isfinite(shifted).sum(0)
    best = shifted.argmin(0)  # the first of equal minima: raster order, as the kernel
    crack = holes.reshape(H, W) & (zb == 0) & (count >= 5)
    ys, xs = torch.nonzero(crack, as_tuple=True)
    off = torch.tensor(_NB8, device=dev)[best[ys, xs]]
    yy, xx = ys + off[:, 0], xs + off[:, 1]
    zb[ys, xs], cb[ys, xs], sb[ys, xs] = zb[yy, xx], cb[yy, xx], sb[yy, xx]
    filled = (zb > 0).cpu().numpy()
    target.depth_m[filled] = zb.cpu().numpy()[filled].astype(np.float32)
    target.color[filled] = cb.cpu().numpy()[filled]
    target.source[filled] = sb.cpu().numpy()[filled]
    target.holes[filled] = 0
    return int(filled.sum())
